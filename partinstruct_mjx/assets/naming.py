"""Naming convention for part-labelled geoms in object MJCF: "<part>/col<k>" collides, "<part>/vis<k>" is visual.

Part labels may contain spaces ("containing things"); in names they are written with underscores.
"""

from __future__ import annotations

COLLISION_TAG = "col"
VISUAL_TAG = "vis"


def part_slug(label: str) -> str:
    """The form of a part label used inside MJCF names."""
    return label.strip().lower().replace(" ", "_")


def geom_name(label: str, kind: str, index: int) -> str:
    """Name of the `index`-th collision (kind "col") or visual (kind "vis") geom of a part."""
    return f"{part_slug(label)}/{kind}{index}"


def parse_geom_name(name: str) -> tuple[str, str] | None:
    """Return (part label, kind) of a part geom name, ignoring any attach prefix; None if not a part geom."""
    pieces = name.rsplit("/", 2)
    if len(pieces) < 2:
        return None
    slug, tail = pieces[-2], pieces[-1]
    for kind in (COLLISION_TAG, VISUAL_TAG):
        if tail.startswith(kind) and tail[len(kind):].isdigit():
            return slug.replace("_", " "), kind
    return None
