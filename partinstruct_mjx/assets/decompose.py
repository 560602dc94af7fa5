"""Convex decomposition of part meshes with CoACD under hard budgets, and a content-hash cache of the results.

Budgets keep objects fast in MJX (DESIGN.md): hulls per part, hulls per object, vertices per hull.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from partinstruct_mjx.assets.geometry import MeshPiece
from partinstruct_mjx.assets.surface import area_samples
from partinstruct_mjx.atomic import atomic_write
from partinstruct_mjx.errors import AssetError

CONVERTER_VERSION = "6"
"""Bumped whenever a change alters the converter's hulls for the same source object (the budgets' rule included)."""

DECOMPOSITION_VERSION = "4"
"""Bumped whenever `decompose` changes its hulls for the same mesh, budget and settings (the part cache's key)."""

CONCAVE_GAP = 0.006
"""A part whose single convex hull lies farther than this (m, the 95th percentile over the hull's surface) from the
part's own surface is concave: one hull would fill what it encloses (the arc of a handle, the loop of a bucket's
bail) and fingers closing on the part would meet that phantom solid instead."""

CONCAVE_PART_HULLS = 6
"""Hulls a concave part may take from the object's spare budget; CoACD stops at fewer where they fit (a kettle's
handle: 4 hulls, 3.5 mm)."""

MIN_THICKNESS = 1e-3
"""Flat hulls (e.g. a single quad) are thickened to this many metres so MuJoCo can compute their volume."""

Hull = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class DecompositionConfig:
    """CoACD settings and budgets. The defaults are the quality preset; see `preset()` for the others."""

    max_hulls_per_part: int = 8
    max_hulls_per_object: int = 16
    max_hull_vertices: int = 32
    threshold: float = 0.08
    preprocess_resolution: int = 50
    resolution: int = 2000
    mcts_iterations: int = 150
    mcts_nodes: int = 20
    mcts_max_depth: int = 3
    seed: int = 0

    @classmethod
    def fast(cls) -> DecompositionConfig:
        """Seconds per object: tests and previews."""
        return cls(threshold=0.25, preprocess_resolution=25, resolution=400, mcts_iterations=20, mcts_nodes=8,
                   mcts_max_depth=2)

    @classmethod
    def balanced(cls) -> DecompositionConfig:
        """About 2.7x faster than quality on the built-in objects, with the same budgets."""
        return cls(threshold=0.1, preprocess_resolution=40, resolution=1000, mcts_iterations=60, mcts_nodes=15)

    @classmethod
    def preset(cls, name: str) -> DecompositionConfig:
        """'quality' (the defaults), 'balanced' or 'fast'."""
        presets = {"quality": cls, "balanced": cls.balanced, "fast": cls.fast}
        if name not in presets:
            raise AssetError(f"unknown decomposition preset '{name}'; choose from {', '.join(presets)}")
        return presets[name]()


def hull_budgets(areas: list[float], config: DecompositionConfig, gaps: list[float] | None = None) -> list[int]:
    """Hulls allowed per part: proportional to surface area, at least one, within both budgets. A part left with one
    hull is not decomposed at all; where that hull strays more than CONCAVE_GAP from the part's surface (`gaps`,
    `single_hull_gap`) the object's spare hulls go to it instead, one at a time, widest gap first, up to
    CONCAVE_PART_HULLS each."""
    if len(areas) > config.max_hulls_per_object:
        raise AssetError(f"{len(areas)} collision parts exceed the budget of {config.max_hulls_per_object} hulls "
                         f"per object")
    share = np.asarray(areas, dtype=float) / max(float(np.sum(areas)), 1e-12)
    budgets = np.clip(np.floor(share * config.max_hulls_per_object), 1, config.max_hulls_per_part).astype(int)
    while budgets.sum() > config.max_hulls_per_object:
        budgets[np.argmax(budgets)] -= 1
    if gaps:
        cap = min(CONCAVE_PART_HULLS, config.max_hulls_per_part)
        concave = [i for i in np.argsort(-np.asarray(gaps), kind="stable") if budgets[i] == 1 and gaps[i] > CONCAVE_GAP]
        while True:
            wanting = [i for i in concave if budgets[i] < cap]
            spare = config.max_hulls_per_object - int(budgets.sum())
            if not wanting or spare <= 0:
                break
            for i in wanting[:spare]:
                budgets[i] += 1
    return budgets.tolist()


def separate_sources(pieces: list[MeshPiece], gaps: list[float], max_units: int) -> tuple[list[MeshPiece], list[float]]:
    """Collision units to decompose, and their `single_hull_gap`s: `pieces`, except that a part whose one hull strays
    more than CONCAVE_GAP from its surface while each of its source meshes fits one hull (a kettle's body and its
    spout, a monitor's housing and the bulge on its back, a pot lid's dome and knob) becomes one unit per source mesh,
    widest gap first while the units fit `max_units`. Decomposed whole, CoACD (held to the part's budget) merged hulls
    across the sources and filled what lies between them: a wedge 3 cm deep from a kettle's belly to its spout tip."""
    units: list[list[MeshPiece]] = [[piece] for piece in pieces]
    unit_gaps: list[list[float]] = [[gap] for gap in gaps]
    count = len(pieces)
    for i in np.argsort(-np.asarray(gaps, dtype=float), kind="stable"):
        if gaps[i] <= CONCAVE_GAP:
            break
        sources = pieces[i].sources()
        if len(sources) < 2 or count + len(sources) - 1 > max_units:
            continue
        source_gaps = [single_hull_gap(s.vertices, s.faces) for s in sources]
        if max(source_gaps) <= CONCAVE_GAP:
            units[i], unit_gaps[i] = sources, source_gaps
            count += len(sources) - 1
    return [u for group in units for u in group], [g for group in unit_gaps for g in group]


def single_hull_gap(vertices: np.ndarray, faces: np.ndarray, samples: int = 2000) -> float:
    """How far (m) a part's convex hull strays from the part's surface: the 95th percentile, over points spread
    evenly on the hull's surface, of the distance to the nearest of 4x as many points on the part's own surface."""
    from scipy.spatial import cKDTree

    part = trimesh.Trimesh(vertices, faces, process=False)
    if part.area <= 0:
        return 0.0
    rng = np.random.default_rng(0)
    hull = trimesh.convex.convex_hull(_thicken(np.unique(np.asarray(vertices, float), axis=0)))
    on_part, _ = area_samples(part.triangles, 4 * samples, rng)
    on_hull, _ = area_samples(hull.triangles, samples, rng)
    distances, _ = cKDTree(on_part).query(on_hull)
    return float(np.percentile(distances, 95))


def decomposition_key(vertices: np.ndarray, faces: np.ndarray, budget: int, config: DecompositionConfig) -> str:
    """Content hash of a decomposition job: the mesh bytes, the budget and every setting."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(faces, dtype=np.int64).tobytes())
    digest.update(json.dumps([DECOMPOSITION_VERSION, budget, dataclasses.asdict(config)], sort_keys=True).encode())
    return digest.hexdigest()


def decompose(vertices: np.ndarray, faces: np.ndarray, budget: int, config: DecompositionConfig) -> list[Hull]:
    """Split a part mesh into at most `budget` convex hulls of at most `config.max_hull_vertices` vertices each."""
    if budget == 1:
        hulls = [(vertices, faces)]
    else:
        import coacd

        coacd.set_log_level("error")
        hulls = coacd.run_coacd(
            coacd.Mesh(np.asarray(vertices, float), np.asarray(faces, np.int64)), threshold=config.threshold,
            max_convex_hull=budget, preprocess_resolution=config.preprocess_resolution, resolution=config.resolution,
            mcts_iterations=config.mcts_iterations, mcts_nodes=config.mcts_nodes, mcts_max_depth=config.mcts_max_depth,
            max_ch_vertex=config.max_hull_vertices, seed=config.seed)
    return [_convex(np.asarray(v, float), config.max_hull_vertices) for v, _ in hulls[:budget]]


def _convex(points: np.ndarray, max_vertices: int) -> Hull:
    """Convex hull of `points` with at most `max_vertices` vertices (`_reduced`), never flat."""
    points = _thicken(np.unique(points, axis=0))
    hull = trimesh.convex.convex_hull(points)
    if len(hull.vertices) > max_vertices:
        hull = trimesh.convex.convex_hull(_reduced(np.asarray(hull.vertices), max_vertices))
    return np.asarray(hull.vertices, float), np.asarray(hull.faces, np.int32)


FACE_TOLERANCE = 5e-4
"""Vertices within this (m) of a hull's extreme along an axis belong to its face there."""


def _reduced(points: np.ndarray, count: int) -> np.ndarray:
    """`count` of a hull's vertices: first the corners of its six axis-aligned faces (the outermost face vertices
    along the face's diagonals), so that a flat base keeps its rim and its height (farthest points alone left a
    bottle's flat base one vertex, and it fell over), then farthest points from those."""
    diagonals = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])
    seeds: list[int] = []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        for sign in (1.0, -1.0):
            height = sign * points[:, axis]
            face = np.flatnonzero(height >= height.max() - FACE_TOLERANCE)
            corners = face[np.argmax(points[face][:, others] @ diagonals.T, axis=0)]
            seeds.extend(int(i) for i in corners)
    seeds = list(dict.fromkeys(seeds))[:count]
    return points[_farthest_points(points, count, seeds)]


def _thicken(points: np.ndarray) -> np.ndarray:
    centred = points - points.mean(axis=0)
    _, singular, axes = np.linalg.svd(centred, full_matrices=False)
    thickness = np.ptp(centred @ axes[-1]) if len(points) > 2 else 0.0
    if len(points) >= 4 and thickness >= MIN_THICKNESS and singular[-1] > 0:
        return points
    normal = axes[-1] if len(axes) == 3 else np.array([0.0, 0.0, 1.0])
    offset = 0.5 * MIN_THICKNESS * normal
    return np.concatenate([points + offset, points - offset])


def _farthest_points(points: np.ndarray, count: int, chosen: list[int]) -> list[int]:
    """Indices of `count` points: `chosen`, then each next one the farthest from those taken."""
    chosen = list(chosen)
    distance = np.min([np.linalg.norm(points - points[i], axis=1) for i in chosen], axis=0)
    while len(chosen) < count:
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return chosen


class HullCache:
    """Decompositions stored by content hash as .npz files; writes are atomic, so a killed run leaves no partial entry."""

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)

    def get(self, key: str) -> list[Hull] | None:
        entry = self.get_with_seconds(key)
        return None if entry is None else entry[0]

    def get_with_seconds(self, key: str) -> tuple[list[Hull], float] | None:
        """The hulls and the seconds their decomposition took, or None if not cached."""
        path = self.directory / f"{key}.npz"
        if not path.is_file():
            return None
        with np.load(path) as data:
            count = int(data["count"])
            return [(data[f"v{i}"], data[f"f{i}"]) for i in range(count)], float(data["seconds"])

    def put(self, key: str, hulls: list[Hull], seconds: float) -> None:
        arrays = {"count": np.array(len(hulls)), "seconds": np.array(seconds)}
        for i, (v, f) in enumerate(hulls):
            arrays[f"v{i}"], arrays[f"f{i}"] = v, f
        with atomic_write(self.directory / f"{key}.npz", "wb") as file:
            np.savez(file, **arrays)
