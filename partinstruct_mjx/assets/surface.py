"""Fixed-seed surface points with normals per part and for the whole object (written to parts.npz).

Points are expressed in the frame of the body they lie on (articulated parts move with their link); each point
carries the index of its body in `body_names`.
"""

from __future__ import annotations

import numpy as np

from partinstruct_mjx.assets.geometry import AssembledObject, MeshPiece
from partinstruct_mjx.assets.partnet import is_semantic_label


def semantic_parts(obj: AssembledObject) -> list[str]:
    """Part labels in order of appearance, without the dataset's 'other' leaves (spec 3.2)."""
    labels = []
    for piece in obj.collision:
        if is_semantic_label(piece.part) and piece.part not in labels:
            labels.append(piece.part)
    return labels


def sample_parts(obj: AssembledObject, points_per_part: int, object_points: int, seed: int) -> dict[str, np.ndarray]:
    """Arrays for parts.npz: per-part and whole-object points, normals and body indices."""
    body_names = [b.name for b in obj.bodies]
    rng = np.random.default_rng(seed)
    parts = semantic_parts(obj)
    sampled = [_sample([p for p in obj.collision if p.part == label], body_names, points_per_part, rng)
               for label in parts]
    whole = _sample(obj.collision, body_names, object_points, rng)
    return {
        "part_names": np.array(parts),
        "body_names": np.array(body_names),
        "points": np.stack([s[0] for s in sampled]).astype(np.float32),
        "normals": np.stack([s[1] for s in sampled]).astype(np.float32),
        "point_body": np.stack([s[2] for s in sampled]).astype(np.int16),
        "object_points": whole[0].astype(np.float32),
        "object_normals": whole[1].astype(np.float32),
        "object_point_body": whole[2].astype(np.int16),
    }


def area_samples(triangles: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """`count` points spread uniformly over `triangles` (T, 3, 3), reproducibly from `rng`, and each point's
    triangle index."""
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    areas = 0.5 * np.linalg.norm(cross, axis=1)
    chosen = rng.choice(len(triangles), size=count, p=areas / areas.sum())
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    t = triangles[chosen]
    points = (1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1] + (r1 * r2)[:, None] * t[:, 2]
    return points, chosen


def _sample(pieces: list[MeshPiece], body_names: list[str], count: int, rng: np.random.Generator):
    triangles = np.concatenate([p.vertices[p.faces] for p in pieces])
    bodies = np.concatenate([np.full(len(p.faces), body_names.index(p.body)) for p in pieces])
    points, chosen = area_samples(triangles, count, rng)
    t = triangles[chosen]
    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    normals = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-12)
    return points, normals, bodies[chosen]
