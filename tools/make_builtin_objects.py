#!/usr/bin/env python3
"""Build the built-in object library in one command: generate, convert, assign splits, draw docs/objects.png.

    python tools/make_builtin_objects.py                    # the committed library (about 20 min on 2 cores)
    python tools/make_builtin_objects.py --categories mug --instances 2 --out /tmp/assets --sheet - --report -

Steps: write PartNet-Mobility-format folders (seeded; same seed -> byte-identical files) under --sources, convert
them with scale 1 (they are in metres) into --out, record split membership in <out>/catalog.json, render the
contact sheet, and write the measured times to the benchmark report.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from partinstruct_mjx.assets.builtin_library import build_library, builtin_convert_config  # noqa: E402
from partinstruct_mjx.assets.catalog import load_catalog  # noqa: E402
from partinstruct_mjx.assets.convert import summary_table  # noqa: E402
from partinstruct_mjx.assets.procedural import CATEGORIES  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("assets_mjcf"), help="assets root (default assets_mjcf)")
    parser.add_argument("--sources", type=Path, default=Path("build/builtin_partnet"),
                        help="where the generated PartNet-format folders go (default build/builtin_partnet)")
    parser.add_argument("--seed", type=int, default=0, help="library seed (>= 0)")
    parser.add_argument("--instances", type=int, default=8, help="instances per category (default 8)")
    parser.add_argument("--categories", nargs="+", metavar="SLUG", help=f"subset of: {' '.join(CATEGORIES)}")
    parser.add_argument("--preset", choices=["quality", "balanced", "fast"], default="balanced",
                        help="CoACD settings (default balanced)")
    parser.add_argument("--workers", type=int, default=None, help="decomposition processes (default: cores)")
    parser.add_argument("--sheet", default="docs/objects.png", help="contact sheet path, '-' to skip")
    parser.add_argument("--report", default="docs/benchmarks.md", help="benchmark report to update, '-' to skip")
    args = parser.parse_args(argv)
    command = " ".join(["python tools/make_builtin_objects.py", *(argv if argv is not None else sys.argv[1:])])
    try:
        build = build_library(args.out, args.sources, args.seed, args.instances, args.categories,
                              builtin_convert_config(args.preset, args.workers))
    except ValueError as error:
        parser.error(str(error))
    print(summary_table(build.records))
    sheet_seconds = 0.0
    if args.sheet != "-":
        from partinstruct_mjx.assets.contact_sheet import contact_sheet

        start = time.perf_counter()
        first = {}
        for entry in load_catalog(args.out):
            first.setdefault(entry["category"], entry)
        tiles = [(f"{e['category']} ({e['id']})", args.out / e["path"] / "object.xml") for e in first.values()]
        contact_sheet(tiles).save(args.sheet)
        sheet_seconds = time.perf_counter() - start
        print(f"wrote {args.sheet}")
    if args.report != "-":
        _report(args.report, command, build, sheet_seconds)
    return 1 if any(r.status == "failed" for r in build.records) else 0


def _report(path: str, command: str, build, sheet_seconds: float) -> None:
    from partinstruct_mjx.bench.report import provenance_lines, write_section
    from partinstruct_mjx.provenance import provenance

    records = build.records
    hulls = [r.hulls for r in records if r.status != "failed"]
    body = (
        "## Built-in object library (generate + convert from scratch)\n\n" + provenance_lines(provenance(), command) +
        f"\n| step | seconds |\n|---|---|\n| generate {len(records)} PartNet-format objects | "
        f"{build.generate_seconds:.1f} |\n| convert (CoACD, empty cache unless re-run) | {build.convert_seconds:.1f} |\n"
        f"| contact sheet | {sheet_seconds:.1f} |\n\n"
        f"{sum(r.status == 'converted' for r in records)} converted, {sum(r.status == 'cached' for r in records)} "
        f"cached, {sum(r.status == 'failed' for r in records)} failed; hulls per object {min(hulls)}-{max(hulls)} "
        f"(mean {sum(hulls) / len(hulls):.1f}).\n")
    write_section(Path(path), "builtin_objects", body)
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())
