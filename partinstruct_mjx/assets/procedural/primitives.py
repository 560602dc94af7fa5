"""Closed triangle meshes built from stacks of rings: loft, lathe (profile revolution), sweep, plus 2-D outlines.

Every mesh returned here is watertight with outward-facing, consistently wound triangles. Ring outlines must be
star-shaped about their centroid (the end caps are triangle fans to it) and share one orientation within a loft.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import trimesh

Array = np.ndarray


def circle(radius: float, segments: int = 48) -> Array:
    """(segments, 2) points of a circle, counter-clockwise, starting on +x."""
    return ellipse(radius, radius, segments)


def ellipse(a: float, b: float, segments: int = 48) -> Array:
    """(segments, 2) points of an axis-aligned ellipse with semi-axes a (x) and b (y), counter-clockwise."""
    t = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    return np.column_stack([a * np.cos(t), b * np.sin(t)])


def superellipse(a: float, b: float, exponent: float, segments: int = 48) -> Array:
    """(segments, 2) points of |x/a|^p + |y/b|^p = 1 (p=2: ellipse, p>=4: rounded rectangle), counter-clockwise.

    Points are indexed by the same angles as `ellipse`, so rings of either kind can be blended point by point.
    """
    t = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    c, s = np.cos(t), np.sin(t)
    power = 2.0 / exponent
    return np.column_stack([a * np.sign(c) * np.abs(c) ** power, b * np.sign(s) * np.abs(s) ** power])


def rounded_rect(size_x: float, size_y: float, radius: float, corner_segments: int = 6) -> Array:
    """Counter-clockwise outline of a rectangle centred at the origin with corners rounded by `radius` (> 0).

    The point count (4 * (corner_segments + 1)) does not depend on the sizes, so offsets of one rectangle
    (`rounded_rect(w + 2d, h + 2d, r + d)`) are exact parallel curves that loft point by point.
    """
    if radius <= 0.0 or 2.0 * radius > min(size_x, size_y) + 1e-12:
        raise ValueError(f"corner radius {radius} does not fit a {size_x} x {size_y} rectangle")
    hx, hy = size_x / 2.0 - radius, size_y / 2.0 - radius
    points = []
    for k, (cx, cy) in enumerate(((hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy))):
        angles = np.linspace(k * np.pi / 2.0, (k + 1) * np.pi / 2.0, corner_segments + 1)
        points.append(np.column_stack([cx + radius * np.cos(angles), cy + radius * np.sin(angles)]))
    return np.vstack(points)


def loft(rings: Sequence[Array], closed: bool = False) -> trimesh.Trimesh:
    """Skin a sequence of (M, 3) rings into a closed mesh.

    Consecutive rings are joined by quads. An open loft gets flat triangle-fan caps on its first and last ring;
    a closed loft (a torus-like loop) joins the last ring back to the first instead.
    """
    if len(rings) < 2:
        raise ValueError("a loft needs at least two rings")
    stack = np.asarray(rings, dtype=float)
    n_rings, m = stack.shape[0], stack.shape[1]
    i = np.arange(m)
    faces = []
    for k in range(n_rings if closed else n_rings - 1):
        lo, hi = k * m, ((k + 1) % n_rings) * m
        a, b, c, d = lo + i, lo + (i + 1) % m, hi + (i + 1) % m, hi + i
        faces.append(np.column_stack([a, b, c]))
        faces.append(np.column_stack([a, c, d]))
    vertices = stack.reshape(-1, 3)
    if not closed:
        first, last = len(vertices), len(vertices) + 1
        vertices = np.vstack([vertices, stack[0].mean(axis=0), stack[-1].mean(axis=0)])
        top = (n_rings - 1) * m
        faces.append(np.column_stack([np.full(m, first), (i + 1) % m, i]))
        faces.append(np.column_stack([np.full(m, last), top + i, top + (i + 1) % m]))
    mesh = trimesh.Trimesh(vertices=vertices, faces=np.vstack(faces), process=False)
    if mesh.volume < 0.0:
        mesh.faces = np.ascontiguousarray(mesh.faces[:, ::-1])
    return mesh


def lathe(profile: Sequence[tuple[float, float]], outline: Callable[[float], Array]) -> trimesh.Trimesh:
    """Stack the planar outline `outline(d)` at height z for each (d, z) of `profile` and loft the rings.

    With `outline=circle` this is a revolution of the (radius, z) profile; with a rounded rectangle it is the
    same wall profile run around a box. The first and last rings are capped.
    """
    rings = []
    for d, z in profile:
        flat = outline(d)
        rings.append(np.column_stack([flat, np.full(len(flat), z)]))
    return loft(rings)


def revolve(profile: Sequence[tuple[float, float]], segments: int = 48) -> trimesh.Trimesh:
    """Solid of revolution about +z of a (radius, z) profile whose first and last points are capped flat."""
    return lathe(profile, lambda r: circle(r, segments))


def extrude_x(stations: Sequence[tuple[float, Array]]) -> trimesh.Trimesh:
    """Loft (M, 2) cross-sections given in the (y, z) plane at the x positions of `stations`."""
    return loft([np.column_stack([np.full(len(section), x), section]) for x, section in stations])


def sweep(
    path: Array,
    section: Array,
    plane_normal: Sequence[float],
    closed: bool = False,
    scale: Array | None = None,
) -> trimesh.Trimesh:
    """Sweep a (M, 2) cross-section along a planar (N, 3) path lying in the plane with normal `plane_normal`.

    Section coordinates are (u, v): u in the path plane, perpendicular to the path; v along `plane_normal`.
    `scale` (N,) scales the section at each path point (tapering). Open paths are capped at both ends.
    """
    path = np.asarray(path, dtype=float)
    normal = np.asarray(plane_normal, dtype=float)
    normal = normal / np.linalg.norm(normal)
    if closed:
        tangents = np.roll(path, -1, axis=0) - np.roll(path, 1, axis=0)
    else:
        tangents = np.gradient(path, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    sides = np.cross(normal, tangents)
    sides /= np.linalg.norm(sides, axis=1, keepdims=True)
    factors = np.ones(len(path)) if scale is None else np.asarray(scale, dtype=float)
    rings = [
        p + f * (section[:, :1] * u + section[:, 1:] * normal)
        for p, u, f in zip(path, sides, factors, strict=True)
    ]
    return loft(rings, closed=closed)


def moved(
    mesh: trimesh.Trimesh,
    offset: Sequence[float] = (0.0, 0.0, 0.0),
    axis: Sequence[float] | None = None,
    angle: float = 0.0,
    pivot: Sequence[float] = (0.0, 0.0, 0.0),
) -> trimesh.Trimesh:
    """A copy of `mesh` rotated by `angle` about `axis` through `pivot`, then translated by `offset`."""
    out = mesh.copy()
    if axis is not None and angle != 0.0:
        out.apply_transform(trimesh.transformations.rotation_matrix(angle, axis, pivot))
    out.apply_translation(offset)
    return out
