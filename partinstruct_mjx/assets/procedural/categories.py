"""One builder per PartInstruct category: a random instance's links, parts and joints from a numpy Generator.

Design frame: metres, Z up, object front towards -X, resting on z=0 (the writer re-centres). Size ranges drawn:

| category    | overall size                                   | graspable parts (cross-section <= 7 cm)          |
|-------------|------------------------------------------------|--------------------------------------------------|
| scissors    | length 14-21 cm, blades 2-4 mm thick           | blade, handle, screw                             |
| kitchen pot | diameter 14-19 cm, height 7-12 cm, + 2 tabs    | lid (knob 3-4 cm), base body (wall); tabs apart  |
| laptop      | width 22-30 cm, depth 14-22 cm                 | screen frame (5-9 mm lid), base frame (1.2-2 cm) |
| eyeglasses  | width 12-15 cm, temples 12-14.5 cm             | leg, base body                                   |
| bucket      | top diameter 12-19 cm, height 10-18 cm         | handle (wire 4.4-7 mm), base body (wall, rim)    |
| display     | screen 20-28 x 11-18.5 cm, stand 4-8 cm        | base support, surface, frame                     |
| pliers      | length 14-21 cm, 0.8-1.2 cm thick              | leg, outlier, base body                          |
| bottle      | height 15-30 cm, body diameter 5-7 cm          | body, neck, lid, mouth                           |
| knife       | handle 9-16 cm x 1.8-2.8 cm x 0.9-1.3 cm       | base body, rotation blade, translation blade     |
| stapler     | length 12-18 cm, width 3.5-5 cm, height 4-7 cm | lid, body, base body                             |
| kettle      | height 14-20 cm, diameter 12-16 cm             | handle, lid                                      |
| mug         | height 8-12 cm, diameter 6-9 cm                | handle, body                                     |
| box         | 8-14 x 4.5-6 cm, height 4-8 cm                 | rotation lid, base body (walls)                  |
| dispenser   | body diameter 5-6.8 cm, height 13-22 cm        | base body, head, pressing lid, handle, outlier   |
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.interpolate import PchipInterpolator

from partinstruct_mjx.assets.procedural.palette import colour
from partinstruct_mjx.assets.procedural.primitives import extrude_x, moved, revolve, rounded_rect, superellipse
from partinstruct_mjx.assets.procedural.shapes import (
    arc_tube,
    blade,
    cup,
    dome,
    knob,
    loop_handle,
    plate,
    profile_tube,
    ring,
    rod,
    shouldered_body,
    slab,
    tray,
)
from partinstruct_mjx.assets.procedural.spec import Joint, Link, Part, Piece

Rng = np.random.Generator
X, Y, Z = np.eye(3)
ORIGIN = np.zeros(3)
HALF_PI = np.pi / 2.0


def _u(rng: Rng, low: float, high: float) -> float:
    return float(rng.uniform(low, high))


def _part(label: str, rgb: tuple[float, float, float], *meshes: trimesh.Trimesh, group: str | None = None) -> Part:
    return Part(label, tuple(Piece(m, rgb) for m in meshes), group)


def _along_y(mesh: trimesh.Trimesh, sign: float = 1.0) -> trimesh.Trimesh:
    """Turn a +z-pointing piece (rod) to point along sign * y."""
    return moved(mesh, axis=X, angle=-sign * HALF_PI)


def _along_x(mesh: trimesh.Trimesh, sign: float = 1.0) -> trimesh.Trimesh:
    """Turn a +z-pointing piece (rod, slab) to point along sign * x."""
    return moved(mesh, axis=Y, angle=sign * HALF_PI)


def mug(rng: Rng) -> tuple[Link, ...]:
    """Thin-walled mug with a loop handle and a liquid fill ("containing things"); rigid."""
    height, r_bottom = _u(rng, 0.08, 0.12), _u(rng, 0.03, 0.039)
    r_top, bulge = min(r_bottom * _u(rng, 0.95, 1.15), 0.042), _u(rng, 0.0, 0.003)
    wall, floor = _u(rng, 0.003, 0.005), _u(rng, 0.005, 0.008)

    def outer(z: float) -> float:
        s = z / height
        return r_bottom + (r_top - r_bottom) * s + bulge * np.sin(np.pi * s)

    body = cup(outer, height, wall, floor, fillet=_u(rng, 0.002, 0.005))
    handle = loop_handle(lambda z: outer(z) - wall / 2, height * _u(rng, 0.18, 0.3), height * _u(rng, 0.68, 0.85),
                         _u(rng, 0.024, 0.034), Y, Z, ORIGIN, (_u(rng, 0.004, 0.006), _u(rng, 0.005, 0.008)))
    fill = floor + (height - floor) * _u(rng, 0.45, 0.85)
    liquid = revolve([(outer(z) - wall - 0.001, z) for z in np.linspace(floor + 0.0005, fill, 4)])
    glaze = colour(rng, "ceramic")
    return (Link("body", (_part("body", glaze, body), _part("handle", glaze, handle),
                          _part("containing things", colour(rng, "liquid"), liquid))),)


def kettle(rng: Rng) -> tuple[Link, ...]:
    """Bellied kettle with a spout, a side or top handle, and a hinged, fixed or missing lid."""
    height, r_max = _u(rng, 0.14, 0.20), _u(rng, 0.06, 0.08)
    r_open = _u(rng, 0.035, 0.045)
    wall, floor = _u(rng, 0.0025, 0.0035), _u(rng, 0.004, 0.006)
    zs = np.array([0.0, 0.45, 0.8, 0.93, 1.0]) * height
    rs = [r_max * _u(rng, 0.8, 0.95), r_max, r_open + (r_max - r_open) * 0.55, r_open, r_open]
    outer_curve = PchipInterpolator(zs, rs)

    def outer(z: float) -> float:
        return float(outer_curve(z))

    body = cup(outer, height, wall, floor, fillet=_u(rng, 0.004, 0.008), samples=10, segments=40)
    z_spout = height * _u(rng, 0.2, 0.35)
    tip = np.array([-(r_max + _u(rng, 0.035, 0.05)), 0.0, height * _u(rng, 0.85, 1.0)])
    start = np.array([-(outer(z_spout) - wall - 0.004), 0.0, z_spout])
    bend = np.array([-(r_max + 0.01), 0.0, z_spout + 0.12 * height])
    t = np.linspace(0.0, 1.0, 16)[:, None]
    spout_path = (1 - t) ** 2 * start + 2 * t * (1 - t) * bend + t ** 2 * tip
    spout = arc_tube(spout_path, Y, 1.0, scale=np.linspace(_u(rng, 0.009, 0.012), _u(rng, 0.004, 0.006), 16))

    style = ("side-hinged", "side-fixed", "top-fixed", "side-none", "top-none")[
        int(rng.choice(5, p=[0.4, 0.2, 0.2, 0.1, 0.1]))]
    thickness = (_u(rng, 0.006, 0.008), _u(rng, 0.007, 0.01))
    if style.startswith("side"):
        handle = loop_handle(lambda z: outer(z) - wall / 2, height * 0.3, height * 0.8, _u(rng, 0.03, 0.045),
                             X, Z, ORIGIN, thickness)
    else:
        y_end = r_open + _u(rng, 0.008, 0.015)
        shoulder_z = np.linspace(0.45 * height, height, 64)
        z_attach = float(np.interp(y_end, [outer(z) for z in shoulder_z][::-1], shoulder_z[::-1])) - 0.002
        handle = loop_handle(lambda y: z_attach, -y_end, y_end, _u(rng, 0.05, 0.07), Z, Y, ORIGIN, thickness)
    metal, plastic = colour(rng, "metal"), colour(rng, "plastic")
    root_parts = [_part("base body", metal, body, spout), _part("handle", plastic, handle)]
    if style.endswith("none"):
        return (Link("base body", tuple(root_parts)),)

    r_lid, rim, rise = r_open + 0.003, 0.004, _u(rng, 0.008, 0.016)
    lid = _part("lid", metal, moved(dome(r_lid, rim, rise, 0.012), (0, 0, height)),
                moved(knob(_u(rng, 0.004, 0.006), _u(rng, 0.009, 0.013), _u(rng, 0.012, 0.018)),
                      (0, 0, height + rim + rise - 0.0005)))
    if style.endswith("fixed"):
        return (Link("base body", (*root_parts, lid)),)
    hinge = Joint(0, "revolute", (r_lid, 0.0, height), (0.0, 1.0, 0.0), 0.0, _u(rng, 1.2, 1.6))
    return Link("base body", tuple(root_parts)), Link("lid", (lid,), hinge)


def kitchen_pot(rng: Rng) -> tuple[Link, ...]:
    """Cooking pot with two tab handles and a knobbed lid that lifts off on a slider.

    Each tab is a non-semantic part of its own ('other' leaves, spec 3.2), so the converter gives it a hull of its
    own: inside the base body the tabs shared the cup's 8 hulls, and CoACD merged each into a wall hull, a wedge the
    pads squeezed the pot out of. Loop ears were one solid hull each (docs/oracle.md).
    """
    height, radius = _u(rng, 0.07, 0.12), _u(rng, 0.07, 0.09)
    flare, wall, floor = _u(rng, 0.0, 0.005), _u(rng, 0.0025, 0.004), _u(rng, 0.004, 0.006)

    def outer(z: float) -> float:
        return radius + flare * z / height

    body = cup(outer, height, wall, floor, fillet=_u(rng, 0.004, 0.01), samples=3)
    # Tabs 3.5-4.5 cm wide reaching 3-4 cm out, their tops 1.5-2.5 cm under the rim: the pads close across a tab's
    # parallel sides, clear of the wall and the lid's rim.
    z_top, width, reach = height - _u(rng, 0.015, 0.025), _u(rng, 0.035, 0.045), _u(rng, 0.03, 0.04)
    thick, sunk = _u(rng, 0.008, 0.012), 2 * wall
    metal = colour(rng, "metal")
    tabs = [_part(f"other tab {k}", metal, moved(slab(width, reach + sunk, thick, 0.008),
                                                 (0.0, side * (outer(z_top) + (reach - sunk) / 2), z_top - thick)))
            for k, side in enumerate((1.0, -1.0))]
    r_lid, rim, rise = outer(height) + _u(rng, 0.002, 0.004), _u(rng, 0.003, 0.005), _u(rng, 0.008, 0.02)
    lid_shell = moved(dome(r_lid, rim, rise, _u(rng, 0.015, 0.02)), (0, 0, height))
    # A knob 3-4 cm tall: the pads (3.4 cm long) close on its cap with their tips above the domed lid.
    lid_knob = moved(knob(_u(rng, 0.006, 0.009), _u(rng, 0.013, 0.018), _u(rng, 0.03, 0.04)),
                     (0, 0, height + rim + rise - 0.0005))
    lid_colour = colour(rng, "glass") if rng.random() < 0.4 else colour(rng, "metal")
    lid = Part("lid", (Piece(lid_shell, lid_colour), Piece(lid_knob, colour(rng, "rubber"))))
    slider = Joint(0, "prismatic", (0.0, 0.0, height), (0.0, 0.0, 1.0), 0.0, _u(rng, 0.06, 0.1))
    return Link("base body", (_part("base body", metal, body), *tabs)), Link("lid", (lid,), slider)


def bucket(rng: Rng) -> tuple[Link, ...]:
    """Tapered bucket with a rolled rim, two lugs, and a wire bail handle (optionally gripped) on a hinge."""
    height, r_top = _u(rng, 0.10, 0.18), _u(rng, 0.06, 0.095)
    r_bottom, wall, floor = r_top * _u(rng, 0.72, 0.88), _u(rng, 0.002, 0.003), _u(rng, 0.003, 0.005)

    def outer(z: float) -> float:
        return r_bottom + (r_top - r_bottom) * z / height

    bead = _u(rng, 0.002, 0.0035)
    body = [cup(outer, height, wall, floor, fillet=_u(rng, 0.003, 0.008), samples=3),
            moved(ring(r_top - wall / 2, r_top - wall / 2, (bead, bead), samples=48), (0, 0, height - bead))]
    z_lug, lug_r, lug_len = height - _u(rng, 0.015, 0.025), _u(rng, 0.005, 0.007), _u(rng, 0.008, 0.012)
    for side in (1.0, -1.0):
        lug = _along_y(rod(lug_r, lug_len + wall, 16), side)
        body.append(moved(lug, (0.0, side * (outer(z_lug) - wall), z_lug)))
    span = outer(z_lug) + lug_len * 0.6
    wire = _u(rng, 0.0022, 0.0035)
    reach = span * _u(rng, 0.75, 0.95)
    handle = [loop_handle(lambda y: z_lug, -span, span, reach, Z, Y, ORIGIN, (wire, wire), samples=32)]
    if rng.random() < 0.6:
        grip = _u(rng, 0.06, 0.085)
        handle.append(moved(_along_y(rod(_u(rng, 0.008, 0.011), grip, 20)), (0.0, -grip / 2, z_lug + reach)))
    hinge = Joint(0, "revolute", (0.0, 0.0, z_lug), (0.0, 1.0, 0.0), -1.45, 1.45)
    return (Link("base body", (_part("base body", colour(rng, "plastic"), *body),)),
            Link("handle", (_part("handle", colour(rng, "metal"), *handle),), hinge))


def bottle(rng: Rng) -> tuple[Link, ...]:
    """Solid bottle: shouldered body (round, oval or squarish) plus one of several neck/mouth/lid stacks; rigid."""
    stack = (("neck", "lid"), ("neck", "mouth"), ("mouth",), ("neck", "mouth", "lid"), ("lid",))[int(rng.integers(5))]
    a = _u(rng, 0.025, 0.035)
    square = rng.random() < 0.35
    b, exponent = (a * _u(rng, 0.75, 1.0), _u(rng, 3.0, 5.0)) if square else (a, 2.0)
    neck_r = _u(rng, 0.009, 0.014)
    neck_h = _u(rng, 0.03, 0.08) if "neck" in stack else 0.0
    mouth_h = _u(rng, 0.008, 0.014) if "mouth" in stack else 0.0
    lid_h = _u(rng, 0.015, 0.03) if "lid" in stack else 0.0
    body_h = max(_u(rng, 0.15, 0.28) - neck_h - mouth_h - lid_h, 0.10)
    top_r = min(neck_r * _u(rng, 1.0, 1.25) if "neck" in stack else _u(rng, 0.013, 0.02), min(a, b) - 0.003)
    material = "glass" if rng.random() < 0.5 else "plastic"
    parts = [_part("body", colour(rng, material), shouldered_body(a, b, exponent, body_h,
                                                                   body_h * _u(rng, 0.15, 0.3), top_r))]
    z, radius = body_h, top_r
    if neck_h:
        parts.append(_part("neck", parts[0].pieces[0].rgb,
                           revolve([(top_r, z), (neck_r, z + neck_h * 0.6), (neck_r, z + neck_h)], 40)))
        z, radius = z + neck_h, neck_r
    if mouth_h:
        mouth_r = radius + _u(rng, 0.0008, 0.002)
        profile = [(mouth_r - 0.0006, z), (mouth_r, z + mouth_h * 0.25), (mouth_r, z + mouth_h * 0.75),
                   (mouth_r - 0.0006, z + mouth_h)]
        parts.append(_part("mouth", parts[0].pieces[0].rgb, revolve(profile, 40)))
        z, radius = z + mouth_h, mouth_r
    if lid_h:
        lid_r = radius + _u(rng, 0.001, 0.003)
        parts.append(_part("lid", colour(rng, "plastic"),
                           revolve([(lid_r, z), (lid_r, z + lid_h - 0.002), (lid_r - 0.002, z + lid_h)], 40)))
    return (Link("body", tuple(parts)),)


def box(rng: Rng) -> tuple[Link, ...]:
    """Open rounded box with a lid hinged at the back: a skirted cap or a flat overhanging panel, with a pull tab.
    At most 6 cm wide (7 cm with the lid), so the Panda's 8 cm opening closes across it."""
    size_x, size_y, height = _u(rng, 0.08, 0.14), _u(rng, 0.045, 0.06), _u(rng, 0.04, 0.08)
    corner, wall, floor = _u(rng, 0.006, 0.015), _u(rng, 0.003, 0.005), _u(rng, 0.003, 0.005)
    base = tray(size_x, size_y, corner, height, wall, floor)
    top = _u(rng, 0.003, 0.005)
    if rng.random() < 0.5:
        clear, lid_wall, skirt = 0.0008, _u(rng, 0.0025, 0.004), _u(rng, 0.012, 0.022)
        grow = clear + lid_wall
        cap = tray(size_x + 2 * grow, size_y + 2 * grow, corner + grow, skirt + top, lid_wall, top)
        lid = moved(cap, (0, 0, height + top), axis=X, angle=np.pi)
        hinge_z = height - skirt
    else:
        grow = _u(rng, 0.0, 0.004)
        lid = moved(slab(size_x + 2 * grow, size_y + 2 * grow, top, corner + grow, 0.001), (0, 0, height))
        hinge_z = height
    tab = moved(slab(0.014, _u(rng, 0.02, 0.035), top, 0.003), (-(size_x / 2 + grow), 0.0, height))
    hinge = Joint(0, "revolute", (size_x / 2 + grow, 0.0, hinge_z), (0.0, 1.0, 0.0), 0.0, _u(rng, 1.6, 2.0))
    material = "wood" if rng.random() < 0.4 else "plastic"
    return (Link("base body", (_part("base body", colour(rng, material), base),)),
            Link("rotation lid", (_part("rotation lid", colour(rng, material), lid, tab),), hinge))


def stapler(rng: Rng) -> tuple[Link, ...]:
    """Desk stapler: base plate with anvil, magazine body on a rear post, and a top lid hinged at the back."""
    length, width = _u(rng, 0.12, 0.18), _u(rng, 0.035, 0.05)
    base_h, body_h = _u(rng, 0.008, 0.012), _u(rng, 0.018, 0.026)
    base = slab(length, width, base_h, width * _u(rng, 0.3, 0.45), 0.002)
    anvil = moved(slab(0.02, width * 0.4, 0.0015, 0.003), (-length / 2 + 0.02, 0.0, base_h))
    back = length / 2 - 0.004
    post = moved(slab(0.025, width * 0.6, body_h, 0.004, 0.001), (back - 0.0125, 0.0, base_h))
    mag_len = length * 0.78
    magazine = moved(slab(mag_len, width * 0.55, body_h * 0.65, 0.004, 0.001),
                     (back - mag_len / 2, 0.0, base_h + body_h * 0.35))
    lid_w, lid_h, lid_len = width * _u(rng, 0.7, 0.85), _u(rng, 0.012, 0.02), length * _u(rng, 0.85, 0.95)
    z_lid = base_h + body_h + 0.0005
    arch = superellipse(lid_w / 2, lid_h, _u(rng, 2.5, 4.0), 32)
    arch[:, 1] = np.maximum(arch[:, 1], 0.0)
    xs = back + 0.002 - np.linspace(0.0, lid_len, 10)
    nose = np.array([1, 1, 1, 1, 1, 1, 1, 0.97, 0.88, 0.6])
    lid = extrude_x([(x, arch * [1.0, s] + [0.0, z_lid]) for x, s in zip(xs, nose, strict=True)])
    hinge = Joint(0, "revolute", (back - 0.006, 0.0, z_lid + 0.003), (0.0, 1.0, 0.0), 0.0, _u(rng, 1.0, 1.4))
    shell = colour(rng, "plastic")
    return (Link("base body", (_part("base body", colour(rng, "rubber"), base, anvil),
                               _part("body", colour(rng, "metal"), post, magazine))),
            Link("lid", (_part("lid", shell, lid),), hinge))


def laptop(rng: Rng) -> tuple[Link, ...]:
    """Laptop: base with keyboard and touchpad, screen lid (frame + panel) on a rear hinge, built open."""
    size_y = _u(rng, 0.22, 0.30)
    size_x, base_h = size_y * _u(rng, 0.62, 0.72), _u(rng, 0.012, 0.02)
    corner = _u(rng, 0.006, 0.012)
    base = slab(size_x, size_y, base_h, corner, 0.002)
    kb_x = size_x * _u(rng, 0.38, 0.45)
    keyboard = moved(slab(kb_x, size_y * _u(rng, 0.8, 0.88), 0.001, 0.002),
                     (size_x / 2 - 0.015 - kb_x / 2, 0.0, base_h))
    pad_x = size_x * _u(rng, 0.22, 0.28)
    touchpad = moved(slab(pad_x, size_y * _u(rng, 0.3, 0.4), 0.0008, 0.003),
                     (-size_x / 2 + 0.012 + pad_x / 2, 0.0, base_h))
    gap, lid_t, lid_x = 0.0022, _u(rng, 0.005, 0.009), size_x * _u(rng, 0.96, 1.0)
    hinge = np.array([size_x / 2 - 0.004, 0.0, base_h + gap + lid_t / 2])
    opening = _u(rng, 1.65, 2.0)
    lid_centre = size_x / 2 - lid_x / 2
    frame = moved(slab(lid_x, size_y, lid_t, corner, 0.0015), (lid_centre, 0.0, base_h + gap))
    panel = moved(slab(lid_x * 0.86, size_y * 0.92, 0.0008, 0.002), (lid_centre, 0.0, base_h + gap - 0.0006))
    frame, panel = (moved(m, axis=Y, angle=opening, pivot=hinge) for m in (frame, panel))
    joint = Joint(0, "revolute", tuple(float(v) for v in hinge), (0.0, 1.0, 0.0), -opening,
                  _u(rng, 2.3, 2.6) - opening)
    shell = colour(rng, "metal")
    return (Link("base frame", (_part("base frame", shell, base, group="base_side"),
                                _part("keyboard", colour(rng, "rubber"), keyboard, group="base_side"),
                                _part("touchpad", colour(rng, "metal"), touchpad, group="base_side"))),
            Link("screen", (_part("screen frame", shell, frame, group="screen_side"),
                            _part("screen", colour(rng, "screen"), panel, group="screen_side")), joint))


def display(rng: Rng) -> tuple[Link, ...]:
    """Monitor on a stand: foot plate ("surface"), neck ("base support"), housing ("frame") and panel ("screen")."""
    width = _u(rng, 0.20, 0.28)
    tall, depth, bezel = width * _u(rng, 0.56, 0.66), _u(rng, 0.012, 0.025), _u(rng, 0.006, 0.014)
    foot_x, foot_y, foot_h = _u(rng, 0.07, 0.11), _u(rng, 0.10, 0.16), _u(rng, 0.008, 0.014)
    z_screen = foot_h + _u(rng, 0.03, 0.07)
    z_mid = z_screen + tall / 2
    housing = moved(_along_x(slab(tall, width, depth, _u(rng, 0.004, 0.01), min(0.002, depth * 0.2))),
                    (-depth / 2, 0.0, z_mid))
    bulge_d = depth * _u(rng, 0.4, 0.8)
    bulge = moved(_along_x(slab(tall * 0.5, width * 0.5, bulge_d + 0.001, 0.01, 0.002)),
                  (depth / 2 - 0.001, 0.0, z_screen + tall * 0.45))
    panel = moved(_along_x(slab(tall - 2 * bezel, width - 2 * bezel, 0.0008, 0.002), -1.0),
                  (-depth / 2 + 0.0002, 0.0, z_mid))
    neck_t, neck_w = _u(rng, 0.012, 0.02), _u(rng, 0.03, 0.06)
    neck_x, neck_top = depth / 2 + bulge_d + neck_t / 2 - 0.001, z_screen + tall * _u(rng, 0.3, 0.5)
    neck = moved(slab(neck_t, neck_w, neck_top - foot_h + 0.001, min(neck_t, neck_w) * 0.4, 0.0),
                 (neck_x, 0.0, foot_h - 0.001))
    foot = moved(slab(foot_x, foot_y, foot_h, _u(rng, 0.01, min(foot_x, foot_y) * 0.45), 0.002),
                 ((neck_x - depth / 2) / 2, 0.0, 0.0))
    shell = colour(rng, "plastic")
    fixed = Joint(0, "fixed", (neck_x, 0.0, neck_top))
    return (Link("base support", (_part("base support", shell, neck, group="base"),
                                  _part("surface", shell, foot, group="base"))),
            Link("screen", (_part("frame", shell, housing, bulge, group="display_screen"),
                            _part("screen", colour(rng, "screen"), panel, group="display_screen")), fixed))


def eyeglasses(rng: Rng) -> tuple[Link, ...]:
    """Spectacles standing on a table: front (rims, lenses, bridge, end pieces) and two temples on hinges."""
    lens_w, lens_h, bridge = _u(rng, 0.044, 0.054), _u(rng, 0.028, 0.04), _u(rng, 0.014, 0.022)
    exponent, rim_r = _u(rng, 2.0, 4.0), _u(rng, 0.0013, 0.0022)
    rim_tube = (rim_r, rim_r * _u(rng, 1.2, 1.8))
    z_c = lens_h / 2 + rim_r
    z_hinge = z_c + lens_h * _u(rng, 0.2, 0.35)
    end_len, temple = _u(rng, 0.006, 0.01), _u(rng, 0.12, 0.145)
    leg_tube = (_u(rng, 0.002, 0.003), _u(rng, 0.0012, 0.0018))
    front, lenses, legs = [], [], []
    for side in (1.0, -1.0):
        centre = np.array([0.0, side * (bridge / 2 + lens_w / 2), z_c])
        front.append(moved(ring(lens_w / 2, lens_h / 2, rim_tube, exponent, Y, Z), centre))
        lenses.append(moved(plate(superellipse(lens_w / 2, lens_h / 2, exponent, 40), 0.0014, Y, Z), centre))
        # The second temple folds behind the first, so its hinge sits further back.
        x_hinge = 0.006 + (side < 0) * (2 * leg_tube[1] + 0.001)
        y_hinge = side * (bridge / 2 + lens_w + end_len - 0.0015)
        end_x = x_hinge + 0.005
        end_h = _u(rng, 0.006, 0.009)
        front.append(moved(slab(end_x + 0.002, end_len + 0.002, end_h, 0.0009),
                           (end_x / 2 - 0.001, side * (bridge / 2 + lens_w + end_len / 2), z_hinge - end_h / 2)))
        straight = np.linspace(x_hinge - 0.001, x_hinge + 0.75 * temple, 10)
        t = np.linspace(0.0, HALF_PI, 9)[1:]
        bend_x = x_hinge + 0.75 * temple + 0.25 * temple * np.sin(t)
        bend_z = z_hinge - (z_hinge - leg_tube[0] - 0.0003) * (1 - np.cos(t))
        xs, zs = np.concatenate([straight, bend_x]), np.concatenate([np.full(10, z_hinge), bend_z])
        path = np.column_stack([xs, np.full(len(xs), y_hinge), zs])
        leg = arc_tube(path, Y, leg_tube, scale=np.linspace(1.0, 0.8, len(xs)))
        legs.append((leg, Joint(0, "revolute", (x_hinge, y_hinge, z_hinge), (0.0, 0.0, -side), 0.0,
                                _u(rng, 1.45, 1.6))))
    s = np.linspace(0.0, 1.0, 12)
    y_in = bridge / 2 + rim_r * 0.5
    arch = np.column_stack([np.zeros(12), -y_in + 2 * y_in * s,
                            z_c + lens_h * 0.2 + _u(rng, 0.002, 0.007) * np.sin(np.pi * s)])
    front.append(arc_tube(arch, X, (rim_r * 1.1, rim_r * 1.3)))
    frame_rgb, tint = colour(rng, "plastic"), colour(rng, "glass")
    base = Part("base body", tuple(Piece(m, frame_rgb) for m in front) + tuple(Piece(m, tint) for m in lenses))
    return (Link("base body", (base,)),
            *(Link("leg", (_part("leg", frame_rgb, leg),), joint) for leg, joint in legs))


def scissors(rng: Rng) -> tuple[Link, ...]:
    """Scissors lying flat: two blade+handle halves stacked at a screw, the upper half on a hinge."""
    total = _u(rng, 0.14, 0.21)
    blade_len, t, width = total * _u(rng, 0.48, 0.56), _u(rng, 0.0015, 0.0025), _u(rng, 0.010, 0.016)
    ring_a, ring_b, tube_w = _u(rng, 0.012, 0.018), _u(rng, 0.009, 0.013), _u(rng, 0.0025, 0.0035)
    # Moulded finger rings 12-16 mm tall (the blades lie between them): a parallel gripper pinches a ring from above
    # with its pads clear of the table, which a 2-3 mm flat pair of scissors would not allow.
    tube_h = _u(rng, 0.006, 0.008)
    root = 0.01
    ring_x = total - blade_len - ring_a - tube_w
    shank_w, exponent = _u(rng, 0.006, 0.009), _u(rng, 2.0, 2.6)
    steel, grip = colour(rng, "metal"), colour(rng, "plastic")
    tip, drop = (blade_len + root) * _u(rng, 0.25, 0.5), _u(rng, 0.2, 0.5)
    halves = []
    for side, z, turn in ((-1.0, tube_h - t / 2, Y), (1.0, tube_h + t / 2, Z)):
        # Lower half: edge faces -y, ring at -y. Upper half: edge faces +y, ring at +y (opens with +angle).
        flat = moved(blade(blade_len + root, width, t, 0.0004, tip, drop), axis=turn, angle=np.pi)
        cut = moved(flat, (root, -side * width / 2, z))
        ring_y = side * (ring_b + tube_w + _u(rng, 0.001, 0.004))
        s = np.linspace(0.0, 1.0, 8)
        shank_path = np.column_stack([root * 0.3 + (ring_x - ring_a - root * 0.3) * s,
                                      ring_y * np.sin(s * HALF_PI), np.full(8, z)])
        shank = profile_tube(shank_path, Z, shank_w, t)
        loop = moved(ring(ring_a, ring_b, (tube_w, tube_h), exponent), (ring_x, ring_y, tube_h))
        halves.append((_part("blade", steel, cut, group="blade_handle_set"),
                       _part("handle", grip, shank, loop, group="blade_handle_set")))
    bottom = max(0.0, tube_h - t - 0.0004)
    screw = moved(rod(_u(rng, 0.003, 0.0042), tube_h + t + 0.0006 - bottom, 20), (0, 0, bottom))
    hinge = Joint(0, "revolute", (0.0, 0.0, tube_h), (0.0, 0.0, 1.0), 0.0, _u(rng, 0.6, 1.0))
    return (Link("blade", (*halves[0], _part("screw", colour(rng, "metal"), screw))),
            Link("blade", halves[1], hinge))


def pliers(rng: Rng) -> tuple[Link, ...]:
    """Pliers lying flat: pivot boss ("base body"), jaws ("outlier") and grips ("leg"); one half on a hinge."""
    total, t = _u(rng, 0.14, 0.21), _u(rng, 0.004, 0.006)
    jaw_len = total * _u(rng, 0.22, 0.35)
    leg_len = total - jaw_len
    boss_r = _u(rng, 0.007, 0.01)
    w_root, w_tip = _u(rng, 0.007, 0.01), _u(rng, 0.002, 0.004)
    leg_w, spread = _u(rng, 0.009, 0.014), _u(rng, 0.015, 0.03)
    steel, grip = colour(rng, "metal"), colour(rng, "rubber")
    halves = []
    for side in (1.0, -1.0):
        # side = +1: fixed half, jaw on +y, leg on -y. side = -1: hinged half, jaw on -y, leg on +y.
        stations = []
        for s in np.linspace(0.0, 1.0, 8):
            w, h = w_root + (w_tip - w_root) * s, 2 * t * (1.0 - 0.3 * s)
            section = rounded_rect(w, h, min(w, h) * 0.3, 3) + [side * w / 2, t]
            stations.append((0.004 - (jaw_len + 0.004) * s, section))
        jaw = extrude_x(stations)
        s = np.linspace(0.0, 1.0, 14)
        path = np.column_stack([boss_r * 0.5 + (leg_len - boss_r * 0.5) * s,
                                -side * (leg_w / 2 + 0.0005 + spread * s ** 1.4), np.full(14, t)])
        leg = profile_tube(path, Z, leg_w, 2 * t, scale=np.linspace(0.75, 1.0, 14))
        halves.append((_part("outlier", steel, jaw), _part("leg", grip, leg)))
    boss = rod(boss_r, 2 * t + 0.001, 24)
    hinge = Joint(0, "revolute", (0.0, 0.0, t), (0.0, 0.0, 1.0), 0.0, _u(rng, 0.3, 0.5))
    return (Link("base body", (_part("base body", steel, boss), *halves[0])), Link("leg", halves[1], hinge))


def _slotted_handle(rng: Rng, length: float, width: float, scale: float, gap: float,
                    spacer_len: float) -> list[trimesh.Trimesh]:
    """Knife handle lying flat: two scales with a `gap` between them and a spacer along the +y side at the back."""
    corner = width * _u(rng, 0.3, 0.45)
    lower = slab(length, width, scale, corner, 0.001)
    upper = moved(lower, (0, 0, scale + gap))
    spacer = moved(slab(spacer_len, 0.0025, gap, 0.001), (length / 2 - spacer_len / 2 - 0.003,
                                                           width / 2 - 0.00125 - 0.0005, scale))
    return [lower, upper, spacer]


def knife(rng: Rng) -> tuple[Link, ...]:
    """Folding knife (rotation blade on a hinge) or utility knife (translation blade on a slider)."""
    # Handle scales 4.5-6 mm thick: the handle lying flat stands 12-16 mm tall, enough for the pads to pinch it.
    scale, gap = _u(rng, 0.0045, 0.006), _u(rng, 0.003, 0.004)
    z_mid = scale + gap / 2
    handle_rgb, steel = colour(rng, "wood" if rng.random() < 0.5 else "plastic"), colour(rng, "metal")
    if rng.random() < 0.5:
        length, width = _u(rng, 0.09, 0.13), _u(rng, 0.018, 0.026)
        pieces = _slotted_handle(rng, length, width, scale, gap, length * 0.55)
        pivot_x = -length / 2 + width * 0.5
        pieces.append(moved(rod(_u(rng, 0.0025, 0.0035), 2 * scale + gap + 0.001, 16), (pivot_x, 0.0, 0.0)))
        root, blade_w = width * 0.5, min(_u(rng, 0.014, 0.022), width - 0.006)
        blade_len = length * _u(rng, 0.75, 0.9)
        flat = blade(blade_len + root, blade_w, _u(rng, 0.0015, 0.0022), 0.0004,
                     blade_len * _u(rng, 0.25, 0.45), _u(rng, 0.2, 0.5))
        cut = moved(moved(flat, axis=Y, angle=np.pi), (pivot_x + root, blade_w / 2, z_mid))
        joint = Joint(0, "revolute", (pivot_x, 0.0, z_mid), (0.0, 0.0, 1.0), 0.0, _u(rng, 3.08, 3.13))
        label = "rotation blade"
    else:
        length, width = _u(rng, 0.12, 0.16), _u(rng, 0.02, 0.028)
        pieces = _slotted_handle(rng, length, width, scale, gap, length * 0.7)
        pieces.append(moved(slab(0.012, 0.007, 0.004, 0.002), (-length * 0.1, 0.0, 2 * scale + gap)))
        blade_len, blade_w = _u(rng, 0.05, 0.06), min(_u(rng, 0.015, 0.019), width - 0.004)
        flat = blade(blade_len, blade_w, _u(rng, 0.0008, 0.0012), 0.0003, blade_w * _u(rng, 0.5, 0.8), 0.0)
        out = _u(rng, 0.015, 0.025)
        cut = moved(moved(flat, axis=Y, angle=np.pi), (-length / 2 - out + blade_len, blade_w / 2, z_mid))
        joint = Joint(0, "prismatic", (-length / 2, 0.0, z_mid), (-1.0, 0.0, 0.0), -(out - 0.004),
                      _u(rng, 0.006, 0.015))
        label = "translation blade"
    return Link("base body", (_part("base body", handle_rgb, *pieces),)), Link(label, (_part(label, steel, cut),),
                                                                                joint)


def dispenser(rng: Rng) -> tuple[Link, ...]:
    """Soap/spray dispenser: a bottle ("base body") with a pump head, a press-down lid, or a trigger sprayer."""
    body_h, a = _u(rng, 0.10, 0.15), _u(rng, 0.025, 0.034)
    b, exponent = (a, 2.0) if rng.random() < 0.5 else (a * _u(rng, 0.7, 1.0), _u(rng, 3.0, 5.0))
    collar_r, collar_h = _u(rng, 0.012, 0.016), _u(rng, 0.01, 0.015)
    body = shouldered_body(a, b, exponent, body_h, body_h * _u(rng, 0.15, 0.3), collar_r)
    collar = moved(rod(collar_r + 0.003, collar_h, 32), (0, 0, body_h))
    top = body_h + collar_h
    shell, cap = colour(rng, "plastic"), colour(rng, "plastic")
    root = Link("base body", (_part("base body", shell, body, collar),))
    kind = ("pump", "press", "trigger")[int(rng.integers(3))]
    down = (0.0, 0.0, -1.0)
    if kind == "pump":
        stem_h, head_r, head_h = _u(rng, 0.01, 0.02), _u(rng, 0.012, 0.018), _u(rng, 0.012, 0.02)
        stem = moved(rod(_u(rng, 0.003, 0.0045), stem_h + 0.001, 16), (0, 0, top - 0.001))
        head = moved(dome(head_r, head_h * 0.6, head_h * 0.4, head_r * 0.5, 40), (0, 0, top + stem_h))
        z_n, reach = top + stem_h + head_h * 0.35, head_r + _u(rng, 0.02, 0.035)
        xs = -np.linspace(head_r * 0.5, reach, 10)
        nozzle_path = np.column_stack([xs, np.zeros(10), z_n - 0.004 * ((xs + head_r * 0.5) / reach) ** 2])
        nozzle = arc_tube(nozzle_path, Y, _u(rng, 0.003, 0.0045))
        slider = Joint(0, "prismatic", (0.0, 0.0, top), down, 0.0, min(stem_h - 0.002, _u(rng, 0.006, 0.012)))
        return root, Link("head", (_part("head", cap, stem, head), _part("outlier", cap, nozzle)), slider)
    if kind == "press":
        travel, lid_r = _u(rng, 0.005, 0.009), collar_r + _u(rng, 0.004, 0.01)
        rim, rise = _u(rng, 0.008, 0.014), _u(rng, 0.004, 0.01)
        stem = moved(rod(collar_r * 0.6, travel + 0.002, 24), (0, 0, top - 0.001))
        lid = moved(dome(lid_r, rim, rise, lid_r * 0.6), (0, 0, top + travel))
        parts = [_part("pressing lid", cap, stem, lid)]
        if rng.random() < 0.5:
            spout = _along_x(rod(_u(rng, 0.0025, 0.0035), _u(rng, 0.008, 0.014) + 0.004, 16), -1.0)
            parts.append(_part("outlier", cap, moved(spout, (-(lid_r - 0.004), 0.0, top + travel + rim * 0.5))))
        slider = Joint(0, "prismatic", (0.0, 0.0, top + travel), down, 0.0, travel - 0.001)
        return root, Link("pressing lid", tuple(parts), slider)
    trigger_len, trigger_w = _u(rng, 0.028, 0.04), _u(rng, 0.007, 0.01)
    head_bottom = body_h + 0.006 + trigger_len + 0.002
    head_w, head_h = _u(rng, 0.02, 0.028), _u(rng, 0.025, 0.035)
    x_trigger = -(collar_r + 0.017 + trigger_w / 2)
    head_len = max(_u(rng, 0.04, 0.055), -x_trigger + 0.012)
    block = extrude_x([(0.018 - (0.018 + head_len) * s, rounded_rect(head_w, head_h * f, head_w * 0.3, 4)
                        + [0.0, head_bottom + head_h * f / 2]) for s, f in zip(np.linspace(0.0, 1.0, 6),
                                                                            np.linspace(1.0, 0.8, 6), strict=True)])
    shroud = moved(rod(collar_r + 0.001, head_bottom - top + 0.0015, 32), (0, 0, top - 0.001))
    z_nozzle = head_bottom + head_h * 0.4
    nozzle = moved(_along_x(rod(_u(rng, 0.004, 0.006), _u(rng, 0.008, 0.014) + 0.002, 20), -1.0),
                   (-head_len + 0.002, 0.0, z_nozzle))
    s = np.linspace(0.0, 1.0, 10)
    lever_path = np.column_stack([x_trigger - 0.006 * np.sin(np.pi * s), np.zeros(10),
                                  head_bottom + 0.002 - (trigger_len + 0.002) * s])
    lever = profile_tube(lever_path, Y, trigger_w, _u(rng, 0.008, 0.012))
    slider = Joint(0, "prismatic", (0.0, 0.0, head_bottom), down, 0.0, _u(rng, 0.003, 0.004))
    pull = Joint(1, "revolute", (x_trigger, 0.0, head_bottom - 0.001), (0.0, -1.0, 0.0), 0.0, _u(rng, 0.2, 0.3))
    return (root, Link("head", (_part("head", cap, block, shroud), _part("outlier", cap, nozzle)), slider),
            Link("handle", (_part("handle", colour(rng, "plastic"), lever),), pull))


@dataclass(frozen=True)
class Category:
    """A PartInstruct category: PartNet name, allowed part labels, parts a gripper should be able to hold."""

    slug: str
    model_cat: str
    parts: tuple[str, ...]
    graspable: tuple[str, ...]
    build: Callable[[Rng], tuple[Link, ...]]


CATEGORIES: dict[str, Category] = {c.slug: c for c in (
    Category("scissors", "Scissors", ("blade", "handle", "screw"), ("blade", "handle", "screw"), scissors),
    Category("kitchen_pot", "KitchenPot", ("base body", "lid"), ("lid",), kitchen_pot),
    Category("laptop", "Laptop", ("base frame", "screen", "touchpad", "keyboard", "screen frame"),
             ("base frame", "screen frame"), laptop),
    Category("eyeglasses", "Eyeglasses", ("base body", "leg"), ("base body", "leg"), eyeglasses),
    Category("bucket", "Bucket", ("handle", "base body"), ("handle",), bucket),
    Category("display", "Display", ("base support", "surface", "frame", "screen"),
             ("base support", "surface", "frame"), display),
    Category("pliers", "Pliers", ("base body", "leg", "outlier"), ("base body", "leg", "outlier"), pliers),
    Category("bottle", "Bottle", ("mouth", "lid", "body", "neck"), ("mouth", "lid", "body", "neck"), bottle),
    Category("knife", "Knife", ("base body", "translation blade", "rotation blade"),
             ("base body", "translation blade", "rotation blade"), knife),
    Category("stapler", "Stapler", ("base body", "lid", "body"), ("base body", "lid", "body"), stapler),
    Category("kettle", "Kettle", ("handle", "base body", "lid"), ("handle", "lid"), kettle),
    Category("mug", "Mug", ("handle", "body", "containing things"), ("handle",), mug),
    Category("box", "Box", ("rotation lid", "base body"), ("rotation lid",), box),
    Category("dispenser", "Dispenser", ("base body", "pressing lid", "head", "handle", "outlier"),
             ("base body", "pressing lid", "head", "handle", "outlier"), dispenser),
)}
