"""Seeded generation of the built-in object library: pick categories, build instances, write PartNet folders."""

from __future__ import annotations

import zlib
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from partinstruct_mjx.assets.partnet import is_semantic_label
from partinstruct_mjx.assets.procedural.categories import CATEGORIES
from partinstruct_mjx.assets.procedural.partnet_writer import write_partnet
from partinstruct_mjx.assets.procedural.spec import ObjectSpec


def resolve_categories(names: Iterable[str] | None) -> list[str]:
    """Validated category slugs in catalogue order; None means all. Raises ValueError naming unknown ones."""
    if names is None:
        return list(CATEGORIES)
    wanted = list(dict.fromkeys(names))
    unknown = [n for n in wanted if n not in CATEGORIES]
    if unknown:
        raise ValueError(f"unknown categor{'y' if len(unknown) == 1 else 'ies'} {', '.join(map(repr, unknown))}; "
                         f"known: {', '.join(CATEGORIES)}")
    return [slug for slug in CATEGORIES if slug in wanted]


def object_id(category: str, index: int) -> str:
    """Folder name and model id of an instance, e.g. "bottle_003"."""
    return f"{category}_{index:03d}"


def build_object(category: str, index: int, seed: int = 0) -> ObjectSpec:
    """Build instance `index` of `category`. It depends only on (seed, category, index), not on other objects."""
    (slug,) = resolve_categories([category])
    if seed < 0 or index < 0:
        raise ValueError(f"seed and index must be non-negative, got seed={seed}, index={index}")
    entry = CATEGORIES[slug]
    rng = np.random.default_rng([seed, zlib.crc32(slug.encode()), index])
    spec = ObjectSpec(slug, entry.model_cat, object_id(slug, index), seed, entry.build(rng))
    stray = {label for label in spec.labels() - set(entry.parts) if is_semantic_label(label)}
    if stray:
        raise ValueError(f"{spec.object_id}: labels {sorted(stray)} are not {slug} parts {entry.parts}")
    return spec


def generate(out_dir: Path, seed: int = 0, instances: int = 8,
             categories: Iterable[str] | None = None) -> list[tuple[ObjectSpec, Path]]:
    """Write `instances` objects per category under `out_dir/<category>/<object id>/`; return (spec, folder)s."""
    if instances < 1:
        raise ValueError(f"instances must be at least 1, got {instances}")
    written = []
    for slug in resolve_categories(categories):
        for index in range(instances):
            spec = build_object(slug, index, seed)
            written.append((spec, write_partnet(spec, Path(out_dir) / slug / spec.object_id)))
    return written
