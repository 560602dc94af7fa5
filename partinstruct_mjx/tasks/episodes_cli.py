"""`partinstruct episodes`: write seeded episode metadata for the splits, or check an existing metadata file."""

from __future__ import annotations

import argparse
from pathlib import Path

from partinstruct_mjx.assets.catalog import load_catalog
from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.paths import assets_root
from partinstruct_mjx.tasks.episodes import (SPLITS, generate_episodes, read_metadata, summary, validate_episodes,
                                             write_metadata)


def add_episodes_parser(subparsers) -> argparse.ArgumentParser:
    """Register the `episodes` subcommand on the main command's subparsers."""
    parser = subparsers.add_parser(
        "episodes", help="generate episode metadata for the splits, or check a metadata file",
        description="Generate task episodes (object, pose, task type, skill chain, task and skill instructions) for "
                    "the object library in the original's metadata JSON format, deterministically from --seed, and "
                    "print the count per split and task type. With --check, read an existing metadata file (ours or "
                    "the original's), validate every episode against the library and print the same table.",
        epilog="Splits (object membership from catalog.json): train, test1 (new poses) and test3 (held-out part "
               "combinations) use task types 1-10 on the training objects, test4 types 11-16 on them; test2 (held-out "
               "instances) and test5 (held-out categories) use types 1-10 on their own objects.")
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--out", type=Path, metavar="FILE", help="metadata JSON to write (replaced atomically)")
    action.add_argument("--check", type=Path, metavar="FILE", help="metadata JSON to validate instead")
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="seed of every draw (default 0)")
    parser.add_argument("--per-type", type=int, default=2, metavar="N",
                        help="episodes per split, object category and task type (default 2)")
    parser.add_argument("--splits", nargs="+", choices=SPLITS, default=list(SPLITS), metavar="SPLIT",
                        help=f"splits to generate (default all: {' '.join(SPLITS)})")
    parser.add_argument("--assets", type=Path, default=None, metavar="DIR",
                        help="assets root with catalog.json (default: the built-in library)")
    parser.set_defaults(func=run_episodes)
    return parser


def run_episodes(args: argparse.Namespace) -> int:
    """Generate and write, or read and validate; TaskError reaches the main command, which exits 2."""
    root = args.assets or assets_root()
    catalog = load_catalog(root)
    if not catalog:
        raise TaskError(f"{root}: no catalog.json with objects")
    if args.check:
        episodes = read_metadata(args.check)
        try:
            validate_episodes(episodes, catalog)
        except TaskError as err:
            raise TaskError(f"{args.check}: {err}") from None
        print(f"{args.check}: {len(episodes)} episodes, all valid for {root}")
    else:
        episodes = generate_episodes(catalog, root, args.seed, args.per_type, tuple(args.splits))
        write_metadata(episodes, args.out)
        print(f"wrote {len(episodes)} episodes to {args.out} (seed {args.seed})")
    print(summary(episodes))
    return 0
