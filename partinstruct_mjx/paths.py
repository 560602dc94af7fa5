"""Where the shipped MJCF assets live, for editable installs, wheels and an explicit override."""

from __future__ import annotations

import os
from pathlib import Path

from partinstruct_mjx.errors import AssetError

_PACKAGE_DIR = Path(__file__).resolve().parent
ASSETS_ENV_VAR = "PARTINSTRUCT_ASSETS"


def assets_root() -> Path:
    """Return the `assets_mjcf` folder: $PARTINSTRUCT_ASSETS, the copy inside a wheel, or the repository's."""
    override = os.environ.get(ASSETS_ENV_VAR)
    candidates = [Path(override)] if override else [_PACKAGE_DIR / "assets_mjcf", _PACKAGE_DIR.parent / "assets_mjcf"]
    for path in candidates:
        if (path / "robots").is_dir():
            return path
    raise AssetError(f"no assets_mjcf folder with robots/ found; looked in {', '.join(map(str, candidates))}")


def robot_xml() -> Path:
    """The Panda MJCF written for this project."""
    return assets_root() / "robots" / "panda" / "panda.xml"


def default_object_xml() -> Path:
    """The built-in object used when none is given (a two-part test block until the object library exists)."""
    return assets_root() / "objects" / "block" / "test_block" / "object.xml"
