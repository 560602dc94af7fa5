"""In-memory description of a generated object: links of labelled parts made of coloured mesh pieces, and joints.

Geometry and joint data are in the design frame: metres, Z up, the object's front facing -X (PartNet's front after
its URDF root rotation). The writer converts to PartNet's Y-up OBJ frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh

Vec3 = tuple[float, float, float]
JointKind = Literal["fixed", "revolute", "prismatic"]


@dataclass(frozen=True)
class Piece:
    """One closed mesh written as one OBJ file with a single plain colour."""

    mesh: trimesh.Trimesh
    rgb: Vec3


@dataclass(frozen=True)
class Part:
    """A labelled leaf of the part hierarchy; `group` optionally names an intermediate node above it."""

    label: str
    pieces: tuple[Piece, ...]
    group: str | None = None


@dataclass(frozen=True)
class Joint:
    """How a link hangs from its parent link.

    `origin` is a point on the hinge axis (revolute) or the link's reference point (prismatic, fixed).
    Limits are radians for revolute joints and metres for prismatic ones; 0 is the pose the meshes are built in.
    """

    parent: int
    kind: JointKind
    origin: Vec3
    axis: Vec3 = (0.0, 0.0, 1.0)
    lower: float = 0.0
    upper: float = 0.0

    def __post_init__(self) -> None:
        if self.kind != "fixed" and not self.lower < self.upper:
            raise ValueError(f"{self.kind} joint needs lower < upper, got [{self.lower}, {self.upper}]")
        if not np.isclose(np.linalg.norm(self.axis), 1.0):
            raise ValueError(f"joint axis {self.axis} is not a unit vector")


@dataclass(frozen=True)
class Link:
    """A rigid group of parts; the root link has no joint. `label` must be one of its parts' labels."""

    label: str
    parts: tuple[Part, ...]
    joint: Joint | None = None

    def __post_init__(self) -> None:
        if self.label not in {p.label for p in self.parts}:
            raise ValueError(f"link label {self.label!r} is not one of its part labels")


@dataclass(frozen=True)
class ObjectSpec:
    """A whole object: `links[0]` is the root, every other link names an earlier link as its parent.

    `category` is the slug (e.g. "kitchen_pot"), `model_cat` PartNet's CamelCase name (e.g. "KitchenPot").
    """

    category: str
    model_cat: str
    object_id: str
    seed: int
    links: tuple[Link, ...]

    def __post_init__(self) -> None:
        if not self.links or self.links[0].joint is not None:
            raise ValueError(f"{self.object_id}: the first link must be the root (no joint)")
        for index, link in enumerate(self.links[1:], start=1):
            if link.joint is None or not 0 <= link.joint.parent < index:
                raise ValueError(f"{self.object_id}: link {index} must hang from an earlier link")

    def bounds(self) -> np.ndarray:
        """(2, 3) min and max corner of all geometry in the built (joint value 0) pose."""
        vertices = np.vstack([pc.mesh.vertices for link in self.links for part in link.parts for pc in part.pieces])
        return np.stack([vertices.min(axis=0), vertices.max(axis=0)])

    def labels(self) -> set[str]:
        """The part labels used by this object."""
        return {part.label for link in self.links for part in link.parts}
