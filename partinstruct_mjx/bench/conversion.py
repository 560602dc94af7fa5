"""Conversion cost per object: seconds, hulls and vertices at the given settings, measured with an empty cache."""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

from partinstruct_mjx.assets.convert import ConversionRecord, ConvertConfig, convert_objects


def measure(sources: list[Path], config: ConvertConfig) -> tuple[list[ConversionRecord], float]:
    """Convert `sources` into a scratch folder with a fresh decomposition cache; return records and wall seconds."""
    with tempfile.TemporaryDirectory() as scratch:
        config = replace(config, cache_dir=str(Path(scratch) / "cache"))
        start = time.perf_counter()
        records = convert_objects(sources, Path(scratch) / "assets", config, progress=False)
        return records, time.perf_counter() - start


def markdown(records: list[ConversionRecord], wall_seconds: float, config: ConvertConfig) -> str:
    budget = config.decomposition
    rows = "\n".join(f"| {r.object_id} | {r.category} | {r.status} | {r.seconds:.1f} | {r.hulls} | {r.vertices} |"
                     for r in records)
    return (
        f"CoACD threshold {budget.threshold}, budgets: {budget.max_hulls_per_part} hulls per part, "
        f"{budget.max_hulls_per_object} per object, {budget.max_hull_vertices} vertices per hull; "
        f"{config.workers} worker processes; empty cache. Seconds per object = its decompositions (CPU time of one "
        f"worker) + reading, assembling and writing.\n\n"
        "| object | category | status | seconds | hulls | hull vertices |\n|---|---|---|---|---|---|\n" + rows +
        f"\n\nWall time for all {len(records)} objects: {wall_seconds:.1f} s.\n")
