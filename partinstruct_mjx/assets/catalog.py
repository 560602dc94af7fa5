"""assets_mjcf/catalog.json: every converted object with its category, parts, scale, source and split membership."""

from __future__ import annotations

import json
import os
from pathlib import Path

from partinstruct_mjx.atomic import atomic_write
from partinstruct_mjx.errors import AssetError

CATALOG_FILE = "catalog.json"


def load_catalog(root: str | os.PathLike) -> list[dict]:
    """Catalog entries under an assets root (empty if there is no catalog yet)."""
    path = Path(root) / CATALOG_FILE
    if not path.is_file():
        return []
    try:
        return json.loads(path.read_text())["objects"]
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise AssetError(f"{path}: malformed catalog ({err})") from err


def write_catalog(root: str | os.PathLike, entries: list[dict]) -> None:
    """Write the catalog atomically, sorted by category and id."""
    path = Path(root) / CATALOG_FILE
    entries = sorted(entries, key=lambda e: (e["category"], e["id"]))
    with atomic_write(path) as file:
        json.dump({"objects": entries}, file, indent=1)
        file.write("\n")


def update_catalog(root: str | os.PathLike, new_entries: list[dict]) -> None:
    """Add or replace entries (matched by path), keeping the split membership already recorded."""
    entries = {e["path"]: e for e in load_catalog(root)}
    for entry in new_entries:
        old = entries.get(entry["path"], {})
        entries[entry["path"]] = {**entry, "splits": old.get("splits", entry.get("splits", []))}
    write_catalog(root, list(entries.values()))
