"""Reusable object pieces built from the primitives: thin-walled vessels, slabs, rods, loop handles, blades, domes.

All lengths are metres. Pieces are built in a Z-up frame; callers place them with `primitives.moved`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import trimesh

from partinstruct_mjx.assets.procedural.primitives import (
    circle,
    ellipse,
    extrude_x,
    lathe,
    loft,
    revolve,
    rounded_rect,
    superellipse,
    sweep,
)

Profile = list[tuple[float, float]]


def vessel_profile(outer: Callable[[float], float], height: float, wall: float, bottom: float,
                   samples: int = 10, fillet: float = 0.0) -> Profile:
    """(d, z) wall profile of an open-top vessel: up the outside, over a rounded rim, down the inside.

    `outer(z)` is the outside radius (or outline offset) at height z; the wall is `wall` thick horizontally and the
    floor `bottom` thick. `fillet` rounds the outside bottom edge. Loft it with `lathe` (first ring = the
    underside, last ring = the inside floor; both are capped).
    """
    if not 0.0 < bottom < height or wall <= 0.0:
        raise ValueError(f"bad vessel: height {height}, wall {wall}, bottom {bottom}")
    profile: Profile = []
    if fillet > 0.0:
        for t in np.linspace(0.0, np.pi / 2.0, 4, endpoint=False):
            profile.append((outer(0.0) - fillet * (1.0 - np.sin(t)), fillet * (1.0 - np.cos(t))))
    zs = np.linspace(fillet, height, samples)
    profile += [(outer(z), z) for z in zs]
    centre = outer(height) - wall / 2.0
    for t in np.linspace(0.0, np.pi, 7)[1:-1]:
        profile.append((centre + wall / 2.0 * np.cos(t), height + wall / 2.0 * np.sin(t)))
    inner_zs = np.linspace(height, bottom, samples)
    profile += [(outer(z) - wall, z) for z in inner_zs]
    return profile


def cup(outer: Callable[[float], float], height: float, wall: float, bottom: float,
        fillet: float = 0.0, samples: int = 10, segments: int = 48) -> trimesh.Trimesh:
    """Round open-top vessel (mug, pot, bucket, kettle) with the given outside radius function."""
    return revolve(vessel_profile(outer, height, wall, bottom, samples, fillet), segments)


def tray(size_x: float, size_y: float, corner: float, height: float, wall: float, bottom: float) -> trimesh.Trimesh:
    """Open-top rounded-rectangle box with straight walls, bottom at z=0."""
    if corner <= wall:
        raise ValueError(f"tray corner radius {corner} must exceed its wall {wall}")
    profile = vessel_profile(lambda z: 0.0, height, wall, bottom)
    return lathe(profile, lambda d: rounded_rect(size_x + 2 * d, size_y + 2 * d, corner + d))


def slab(size_x: float, size_y: float, height: float, corner: float, bevel: float = 0.0) -> trimesh.Trimesh:
    """Rounded-corner box from z=0 to `height`, centred in x and y, with top and bottom edges chamfered by `bevel`."""
    if bevel >= corner and bevel > 0.0:
        raise ValueError(f"slab bevel {bevel} must be smaller than its corner radius {corner}")
    profile = [(0.0, 0.0), (0.0, height)] if bevel <= 0.0 else [
        (-bevel, 0.0), (0.0, bevel), (0.0, height - bevel), (-bevel, height)]
    return lathe(profile, lambda d: rounded_rect(size_x + 2 * d, size_y + 2 * d, corner + d))


def rod(radius: float, length: float, segments: int = 24) -> trimesh.Trimesh:
    """Cylinder along +z from z=0 to `length`."""
    return revolve([(radius, 0.0), (radius, length)], segments)


def dome(radius: float, rim: float, rise: float, top_radius: float, segments: int = 48) -> trimesh.Trimesh:
    """Solid lid: flat underside at z=0, vertical rim of height `rim`, spherical-ish cap rising `rise` above it."""
    profile: Profile = [(radius, 0.0), (radius, rim)]
    for t in np.linspace(0.0, 1.0, 9)[1:]:
        r = radius + (top_radius - radius) * t
        profile.append((r, rim + rise * np.sin(t * np.pi / 2.0)))
    return revolve(profile, segments)


def knob(stem_radius: float, cap_radius: float, height: float, segments: int = 32) -> trimesh.Trimesh:
    """Mushroom knob standing on z=0: a flared foot, a stem, and a rounded cap of radius `cap_radius`."""
    stem, cap = height * 0.45, height * 0.55
    profile: Profile = [(stem_radius * 1.25, 0.0), (stem_radius, stem * 0.3), (stem_radius, stem),
                        (cap_radius, stem + 0.15 * cap), (cap_radius, stem + 0.5 * cap)]
    end = 0.45 * np.pi
    for t in np.linspace(0.0, end, 6)[1:]:
        profile.append((cap_radius * np.cos(t), stem + 0.5 * cap * (1.0 + np.sin(t) / np.sin(end))))
    return revolve(profile, segments)


def loop_handle(attach: Callable[[float], float], s0: float, s1: float, reach: float,
                outward: np.ndarray, along: np.ndarray, origin: np.ndarray,
                thickness: tuple[float, float], samples: int = 24) -> trimesh.Trimesh:
    """Half-elliptic handle loop (mug/kettle handle, bucket bail, pot ear) leaving and re-entering a surface.

    In the plane spanned by unit vectors `outward` and `along` (through `origin`), the loop runs from s0 to s1 along
    `along`, bulging `reach` beyond the surface whose outward coordinate at s is `attach(s)`; both ends meet the
    surface head-on. The tube cross-section has half-widths `thickness` = (in plane, out of plane).
    """
    t = np.linspace(-np.pi / 2.0, np.pi / 2.0, samples)
    mid, half = (s0 + s1) / 2.0, (s1 - s0) / 2.0
    s = mid + half * np.sin(t)
    u = np.array([attach(v) for v in s]) + reach * np.cos(t)
    path = origin + np.outer(u, outward) + np.outer(s, along)
    section = ellipse(thickness[0], thickness[1], 16)
    return sweep(path, section, np.cross(outward, along))


def arc_tube(points: np.ndarray, plane_normal: np.ndarray, radius: float | tuple[float, float],
             scale: np.ndarray | None = None) -> trimesh.Trimesh:
    """Tube of elliptic section (or round, for a single radius) along an open planar polyline."""
    a, b = (radius, radius) if np.ndim(radius) == 0 else radius
    return sweep(points, ellipse(a, b, 16), plane_normal, scale=scale)


def ring(centre_a: float, centre_b: float, tube: tuple[float, float], exponent: float = 2.0,
         u_axis: Sequence[float] = (1.0, 0.0, 0.0), v_axis: Sequence[float] = (0.0, 1.0, 0.0),
         samples: int = 40) -> trimesh.Trimesh:
    """Closed loop (finger ring, spectacle rim, rim bead) around a superellipse centred at the origin.

    The loop has semi-axes `centre_a` along `u_axis` and `centre_b` along `v_axis`; `tube` = (half-width in the
    loop's plane, half-thickness across it) of the elliptic cross-section.
    """
    flat = superellipse(centre_a, centre_b, exponent, samples)
    path = np.outer(flat[:, 0], u_axis) + np.outer(flat[:, 1], v_axis)
    return sweep(path, ellipse(tube[0], tube[1], 12), np.cross(u_axis, v_axis), closed=True)


def plate(outline: np.ndarray, thickness: float, u_axis: Sequence[float], v_axis: Sequence[float]) -> trimesh.Trimesh:
    """Flat plate (lens, panel) of a (M, 2) outline in the (u, v) plane, `thickness` thick and centred on it."""
    normal = np.cross(u_axis, v_axis)
    flat = np.outer(outline[:, 0], u_axis) + np.outer(outline[:, 1], v_axis)
    return loft([flat - normal * thickness / 2.0, flat + normal * thickness / 2.0])


def shouldered_body(a: float, b: float, exponent: float, height: float, shoulder: float, top_radius: float,
                    segments: int = 48) -> trimesh.Trimesh:
    """Solid bottle body: a superellipse section (round, oval or squarish) rising from z=0 with a bevelled foot,
    then a rounded shoulder over its top `shoulder` that blends into a circle of `top_radius` at `height`."""
    if not 0.0 < shoulder < height or top_radius >= min(a, b):
        raise ValueError(f"bad bottle body: height {height}, shoulder {shoulder}, top radius {top_radius}")
    base = superellipse(a, b, exponent, segments)
    top = circle(top_radius, segments)
    foot = min(0.004, (height - shoulder) / 4.0)
    rings = [(0.0, base * 0.93), (foot, base), (height - shoulder, base)]
    for t in np.linspace(0.0, 1.0, 8)[1:]:
        w = 1.0 - np.cos(t * np.pi / 2.0)
        rings.append((height - shoulder + shoulder * np.sin(t * np.pi / 2.0), (1.0 - w) * base + w * top))
    return loft([np.column_stack([flat, np.full(segments, z)]) for z, flat in rings])


def blade(length: float, width: float, spine: float, edge: float, tip_length: float, tip_drop: float,
          stations: int = 14) -> trimesh.Trimesh:
    """Flat-ground blade lying in the x-y plane from x=0 (root) to x=length (tip), centred on z=0.

    The spine runs along y=0 and is `spine` thick; the cutting edge runs along y=-width and is `edge` thick.
    Over the last `tip_length` the spine drops by `tip_drop` * width while the edge rises to meet it.
    """
    if not 0.0 < tip_length < length or not 0.0 < edge < spine:
        raise ValueError(f"bad blade: length {length}, tip {tip_length}, spine {spine}, edge {edge}")
    body_end = length - tip_length
    xs = np.concatenate([np.linspace(0.0, body_end, 4, endpoint=False), np.linspace(body_end, length, stations - 4)])
    meet = -width * tip_drop
    sections = []
    for x in xs:
        f = min(1.0, max(0.0, (x - body_end) / tip_length))
        y_spine = meet * (1.0 - np.sqrt(1.0 - f * f))
        y_edge = min(-width + (width + meet) * f ** 1.5, y_spine - 4e-4)
        t_spine = max(spine * (1.0 - 0.6 * f), edge * 1.5)
        sections.append((x, np.array([[y_spine, t_spine / 2], [y_edge, edge / 2],
                                      [y_edge, -edge / 2], [y_spine, -t_spine / 2]])))
    return extrude_x(sections)


def profile_tube(path: np.ndarray, plane_normal: np.ndarray, width: float, thickness: float,
                 scale: np.ndarray | None = None) -> trimesh.Trimesh:
    """Bar of rounded-rectangle section (width in the path plane, thickness along the normal) along a path."""
    corner = min(width, thickness) * 0.45
    return sweep(path, rounded_rect(width, thickness, corner, 3), plane_normal, scale=scale)
