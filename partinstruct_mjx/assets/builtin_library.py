"""The built-in object library: generate PartNet-format objects, convert them, assign splits, draw the sheet."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

from partinstruct_mjx.assets.catalog import load_catalog, write_catalog
from partinstruct_mjx.assets.convert import ConversionRecord, ConvertConfig, convert_objects
from partinstruct_mjx.assets.decompose import DecompositionConfig
from partinstruct_mjx.assets.procedural import generate

BUILTIN_POINTS_PER_PART = 1024
BUILTIN_OBJECT_POINTS = 2048
"""Half the converter defaults: keeps the committed library small; point spacing stays under 1 cm on every part."""


@dataclass(frozen=True)
class LibraryBuild:
    records: list[ConversionRecord]
    generate_seconds: float
    convert_seconds: float


def builtin_convert_config(preset: str = "balanced", workers: int | None = None, cache_dir: str | None = None
                           ) -> ConvertConfig:
    """Conversion settings of the built-in objects: metres already (scale 1), `preset` CoACD settings."""
    config = ConvertConfig(scale=1.0, target_size=None, decomposition=DecompositionConfig.preset(preset),
                           points_per_part=BUILTIN_POINTS_PER_PART, object_points=BUILTIN_OBJECT_POINTS)
    changes = {k: v for k, v in {"workers": workers, "cache_dir": cache_dir}.items() if v is not None}
    return replace(config, **changes)


def build_library(out_root: Path, sources: Path, seed: int = 0, instances: int = 8, categories=None,
                  config: ConvertConfig | None = None, progress: bool = True) -> LibraryBuild:
    """Write the PartNet-format sources under `sources`, convert them into `out_root` and record their splits."""
    from partinstruct_mjx.assets.splits import assign_splits

    start = time.perf_counter()
    written = generate(sources, seed, instances, categories)
    generated = time.perf_counter()
    records = convert_objects([folder for _, folder in written], out_root, config or builtin_convert_config(),
                              progress=progress)
    converted = time.perf_counter()
    builtin_ids = {folder.name for folder in Path(sources).glob("*/*") if folder.is_dir()}
    entries = load_catalog(out_root)
    builtin = [e for e in entries if e["id"] in builtin_ids]
    others = [e for e in entries if e["id"] not in builtin_ids]
    write_catalog(out_root, others + assign_splits(builtin, seed=seed))
    return LibraryBuild(records, generated - start, converted - generated)
