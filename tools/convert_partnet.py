#!/usr/bin/env python3
"""Convert PartNet-Mobility folders into MJCF assets; the same as `partinstruct convert` (see --help)."""

import sys

from partinstruct_mjx.cli import main

if __name__ == "__main__":
    sys.exit(main(["convert", *sys.argv[1:]]))
