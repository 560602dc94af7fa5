"""Part point clouds of one object as JAX arrays, and the spatial parts (spec 3.3) computed from them.

Every part is one row of `points`: the semantic parts (parts.npz), then the seven spatial parts (rows holding the
whole-object points; a per-environment mask picks the region), then the whole object (part ''). Points live in the
frame of their body, so articulated parts move with their link and spatial regions stay attached to the object
between resamplings (spec 3.3's freeze semantics).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from flax import struct

from partinstruct_mjx.errors import AssetError, TaskError
from partinstruct_mjx.sim.scene import OBJECT_PREFIX, Scene
from partinstruct_mjx.tasks.vocabulary import DIRECTIONS, SPATIAL_PARTS
from partinstruct_mjx.vectors import dot3, squared_norm

SPATIAL_VARIANCE = 0.2
MIDDLE_VARIANCE = 0.03
"""The original's 'sigma' values, used as variances of the Gaussian score (spec 3.3)."""

_SPATIAL_MEANS = np.array([DIRECTIONS[w] if w in DIRECTIONS else (0.0, 0.0, 0.0) for w in SPATIAL_PARTS])
_SPATIAL_VARIANCES = np.array([MIDDLE_VARIANCE if w == "middle" else SPATIAL_VARIANCE for w in SPATIAL_PARTS])


SEMANTIC_ROWS = 8
"""Rows reserved for semantic parts (a multiple of it for objects with more): objects with different part counts
then give arrays of the same shapes, and jitted functions compiled for one object serve the others."""
GEOM_ROWS = 64
"""`geom_part` is padded to a multiple of this many geoms, for the same reason."""


@struct.dataclass
class PartGeometry:
    """Part clouds of one object (shared by every environment of a batch); the arrays jitted code reads.

    Rows: `num_semantic` semantic parts (the object's, then invalid padding rows), the seven spatial parts, then the
    whole object. points: (K, M, 3) body-frame points per part row; normals: (K, M, 3) their outward unit normals
    (body frame); bodies: (K, M) model body ids; valid: (K, M) padding mask.
    geom_part: (G,) semantic part row of each geom, -1 for geoms that are not the object's (and padding).
    The row labels live in `PartNames` (host side).
    """

    points: jnp.ndarray
    normals: jnp.ndarray
    bodies: jnp.ndarray
    valid: jnp.ndarray
    geom_part: jnp.ndarray
    num_semantic: int = struct.field(pytree_node=False)

    @property
    def whole(self) -> int:
        """Row of the whole object (part '')."""
        return self.points.shape[0] - 1


@dataclass(frozen=True)
class PartNames:
    """The labels of a PartGeometry's rows: the object's semantic parts, the spatial parts and '' (whole object)."""

    semantic: tuple[str, ...]
    num_semantic: int
    """Semantic rows of the geometry (the object's parts, then padding)."""

    @property
    def whole(self) -> int:
        return self.num_semantic + len(SPATIAL_PARTS)

    def index(self, name: str) -> int:
        """Row of a part label, spatial word or '' (whole object); raises TaskError naming an unknown part."""
        name = "" if name in ("", None) else name
        if name in self.semantic:
            return self.semantic.index(name)
        if name in SPATIAL_PARTS:
            return self.num_semantic + SPATIAL_PARTS.index(name)
        if name == "":
            return self.whole
        known = ", ".join((*self.semantic, *SPATIAL_PARTS))
        raise TaskError(f"unknown part '{name}'; this object has: {known}")


def load_parts(scene: Scene, parts_npz: str | Path | None = None) -> tuple[PartGeometry, PartNames]:
    """Read parts.npz next to the scene's object (or `parts_npz`), map its bodies to the scene's body ids and lay the
    rows out as PartGeometry describes."""
    path = Path(parts_npz) if parts_npz else scene.object_xml.parent / "parts.npz"
    if not path.is_file():
        raise AssetError(f"missing part point file: {path}")
    data = np.load(path)
    model = scene.model
    try:
        body_ids = np.array([model.body(OBJECT_PREFIX + str(name)).id for name in data["body_names"]])
    except KeyError as err:
        raise AssetError(f"{path}: body {err} is not in {scene.object_xml}") from err
    names = [str(n) for n in data["part_names"]]
    semantic_rows = -(-max(len(names), 1) // SEMANTIC_ROWS) * SEMANTIC_ROWS
    object_points = data["object_points"]
    m = len(object_points)
    semantic = data["points"][:, :m]
    rows = semantic_rows + len(SPATIAL_PARTS) + 1
    points = np.zeros((rows, m, 3), np.float32)
    normals = np.zeros((rows, m, 3), np.float32)
    bodies = np.zeros((rows, m), np.int32)
    valid = np.zeros((rows, m), bool)
    points[: len(names), : semantic.shape[1]] = semantic
    normals[: len(names), : semantic.shape[1]] = data["normals"][:, :m]
    bodies[: len(names), : semantic.shape[1]] = body_ids[data["point_body"][:, :m]]
    valid[: len(names), : semantic.shape[1]] = True
    points[semantic_rows:] = object_points
    normals[semantic_rows:] = data["object_normals"]
    bodies[semantic_rows:] = body_ids[data["object_point_body"]]
    valid[semantic_rows:] = True
    part_names = PartNames(tuple(names), semantic_rows)
    geom_part = np.full(-(-model.ngeom // GEOM_ROWS) * GEOM_ROWS, -1, np.int32)
    for g in range(model.ngeom):
        if scene.geom_part[g] >= 0:
            label = scene.part_names[scene.geom_part[g]]
            geom_part[g] = names.index(label) if label in names else part_names.whole
    geometry = PartGeometry(jnp.asarray(points), jnp.asarray(normals), jnp.asarray(bodies), jnp.asarray(valid),
                            jnp.asarray(geom_part), num_semantic=semantic_rows)
    return geometry, part_names


def load_part_geometry(scene: Scene, parts_npz: str | Path | None = None) -> PartGeometry:
    """`load_parts` without the labels."""
    return load_parts(scene, parts_npz)[0]


def world_points(body_pos: jnp.ndarray, body_quat: jnp.ndarray, points: jnp.ndarray, bodies: jnp.ndarray):
    """Body-frame points (..., 3) of bodies (...) -> world frame, for one environment's body poses: each body's
    rotation matrix applied per coordinate (a quaternion rotation per point runs as slow concatenations on a CPU)."""
    from partinstruct_mjx.control.rotations import quat_to_matrix

    rotation = quat_to_matrix(body_quat)[bodies]
    return jnp.stack([dot3(rotation[..., i, :], points) for i in range(3)], axis=-1) + body_pos[bodies]


def spatial_masks(object_points_world: jnp.ndarray) -> jnp.ndarray:
    """(7, M) masks of the spatial parts from the whole-object points in world frame (spec 3.3).

    Points are normalised by the world AABB (centre, diagonal), scored by a Gaussian with mean = the word's axis and
    variance 0.2 (0.03 for middle); points scoring at least max - 1.5 std are kept.
    """
    lo, hi = object_points_world.min(axis=0), object_points_world.max(axis=0)
    q = (object_points_world - (lo + hi) / 2) / jnp.maximum(jnp.linalg.norm(hi - lo), 1e-9)
    diff = q[None] - jnp.asarray(_SPATIAL_MEANS)[:, None]
    score = jnp.exp(-0.5 * squared_norm(diff) / jnp.asarray(_SPATIAL_VARIANCES)[:, None])
    threshold = score.max(axis=1, keepdims=True) - 1.5 * score.std(axis=1, keepdims=True)
    return score >= threshold
