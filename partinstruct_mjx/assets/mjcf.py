"""Writing an assembled, decomposed object as MJCF: object.xml plus meshes/ (hull STLs, visual OBJs, PNG textures).

Collision geoms are the convex hulls, named `<part>/col<k>`; visual geoms keep colours and textures, are named
`<part>/vis<k>` and never collide. Mass is spread over the hulls by volume.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from partinstruct_mjx.assets.decompose import Hull
from partinstruct_mjx.assets.geometry import AssembledObject, MeshPiece, quat_wxyz
from partinstruct_mjx.assets.naming import COLLISION_TAG, VISUAL_TAG, geom_name, part_slug
from partinstruct_mjx.errors import AssetError

HELPER_MASS = 1e-4
"""Mass of bodies without collision geometry (e.g. `*_helper` links of screw joints), kg."""


MJCF_VERSION = "2"
"""Bumped whenever a change alters the MJCF written for the same hulls and settings (2: joints hold the heavier
side, 2026-12-01)."""


@dataclass(frozen=True)
class PhysicsConfig:
    """Mass and joint behaviour of converted objects."""

    mass: float = 0.2
    """Total mass in kg (used unless `density` is set)."""
    density: float | None = None
    """kg/m^3 of the collision hulls; overrides `mass`."""
    joint_damping: float = 0.05
    joint_frictionloss: float = 0.02
    """Least dry friction of a joint (N m or N); raised per joint to `hold_factor` x the gravity load it carries."""
    hold_factor: float = 2.0
    """Joints hold this multiple of the weight torque (hinges) or weight (slides) of the heavier side, the subtree or
    the rest of the object, whichever is held: lids do not flop, and a box lifted by its lid does not swing open."""
    joint_armature: float = 0.01
    """Reflected inertia (kg m^2 or kg): MuJoCo's dry friction is a soft constraint and light links creep through it
    (a box lid crept 0.38 rad in 5 s with 1e-4, 0.007 rad with 0.01)."""
    friction: float = 0.5
    """Sliding friction of the object's surfaces (the original's effective 0.5)."""


def write_mjcf(folder: Path, name: str, obj: AssembledObject, hulls: list[list[Hull]], physics: PhysicsConfig) -> dict:
    """Write `folder/object.xml` and `folder/meshes/`; return statistics (hulls, vertices, mass)."""
    meshes = folder / "meshes"
    meshes.mkdir(parents=True, exist_ok=True)
    volumes = [[float(trimesh.Trimesh(v, f).volume) for v, f in part] for part in hulls]
    total_volume = sum(map(sum, volumes))
    if total_volume <= 0:
        raise AssetError(f"{name}: the collision hulls have no volume")
    density = physics.density if physics.density is not None else physics.mass / total_volume

    root = ET.Element("mujoco", model=name)
    ET.SubElement(root, "compiler", angle="radian", meshdir="meshes", texturedir="meshes", autolimits="true")
    default = ET.SubElement(ET.SubElement(root, "default"), "default", {"class": "object"})
    ET.SubElement(default, "joint", damping=_num(physics.joint_damping), frictionloss=_num(physics.joint_frictionloss),
                  armature=_num(physics.joint_armature))
    ET.SubElement(ET.SubElement(default, "default", {"class": "visual"}), "geom", group="2", contype="0",
                  conaffinity="0", density="0")
    ET.SubElement(ET.SubElement(default, "default", {"class": "collision"}), "geom", group="3", contype="2",
                  conaffinity="1", condim="3", friction=f"{_num(physics.friction)} 0.005 0.0001")
    asset = ET.SubElement(root, "asset")
    for key, material in obj.materials.items():
        attributes = {"name": key, "rgba": _vec(material.rgba), "specular": "0.2"}
        if material.texture_png:
            (meshes / f"{key}.png").write_bytes(material.texture_png)
            ET.SubElement(asset, "texture", name=key, type="2d", file=f"{key}.png")
            attributes["texture"] = key
        ET.SubElement(asset, "material", attributes)

    bodies = {}
    world = ET.SubElement(root, "worldbody")
    for body in obj.bodies:
        parent = world if body.parent is None else bodies[body.parent]
        attributes = {"name": body.name, "childclass": "object"}
        if body.parent is not None:
            attributes |= {"pos": _vec(body.transform[:3, 3]), "quat": _vec(quat_wxyz(body.transform))}
        bodies[body.name] = ET.SubElement(parent, "body", attributes)
        if body.joint is not None:
            joint = {"name": body.joint.name, "type": body.joint.kind, "axis": _vec(body.joint.axis),
                     "frictionloss": _num(_holding_friction(obj, hulls, density, body, physics))}
            if body.joint.range is not None:
                joint["range"] = _vec(body.joint.range)
            ET.SubElement(bodies[body.name], "joint", joint)

    counters: dict[tuple[str, str], int] = {}
    stats = {"hulls": 0, "hull_vertices": 0, "max_hull_vertices": 0, "visual_meshes": 0}
    for piece, part_hulls, part_volumes in zip(obj.collision, hulls, volumes):
        for (vertices, faces), volume in zip(part_hulls, part_volumes):
            index = _next(counters, piece.part, COLLISION_TAG)
            mesh_name = f"{COLLISION_TAG}_{part_slug(piece.part)}_{index}"
            (meshes / f"{mesh_name}.stl").write_bytes(trimesh.Trimesh(vertices, faces).export(file_type="stl"))
            ET.SubElement(asset, "mesh", name=mesh_name, file=f"{mesh_name}.stl", maxhullvert=str(len(vertices)))
            ET.SubElement(bodies[piece.body], "geom", {"name": geom_name(piece.part, COLLISION_TAG, index),
                                                        "class": "collision", "type": "mesh", "mesh": mesh_name,
                                                        "mass": _num(density * volume)})
            stats["hulls"] += 1
            stats["hull_vertices"] += len(vertices)
            stats["max_hull_vertices"] = max(stats["max_hull_vertices"], len(vertices))
    for piece in obj.visual:
        index = _next(counters, piece.part, VISUAL_TAG)
        mesh_name = f"{VISUAL_TAG}_{part_slug(piece.part)}_{index}"
        (meshes / f"{mesh_name}.obj").write_text(_obj_text(piece))
        ET.SubElement(asset, "mesh", name=mesh_name, file=f"{mesh_name}.obj", inertia="shell")
        ET.SubElement(bodies[piece.body], "geom", {"name": geom_name(piece.part, VISUAL_TAG, index), "class": "visual",
                                                    "type": "mesh", "mesh": mesh_name, "material": piece.material})
        stats["visual_meshes"] += 1
    for body in obj.bodies:
        element = bodies[body.name]
        has_mass = any(g.get("class") == "collision" for g in element.findall("geom"))
        if body.parent is not None and not has_mass:
            ET.SubElement(element, "inertial", pos="0 0 0", mass=_num(HELPER_MASS), diaginertia="1e-9 1e-9 1e-9")
    ET.indent(root, space="  ")
    (folder / "object.xml").write_text(ET.tostring(root, encoding="unicode") + "\n")
    stats["mass"] = density * total_volume
    return stats


def _holding_friction(obj: AssembledObject, hulls: list[list[Hull]], density: float, body, physics) -> float:
    """Dry friction that holds the joint of `body` against gravity in any orientation of the object, whichever side
    of it is held: the subtree hanging from the rest (a lid, the rest on the table) or the rest hanging from the
    subtree (a box lifted by its lid, a knife by its blade)."""
    world = {}
    for b in obj.bodies:
        world[b.name] = b.transform if b.parent is None else world[b.parent] @ b.transform
    in_subtree = {body.name}
    for b in obj.bodies:
        if b.parent in in_subtree:
            in_subtree.add(b.name)
    to_body = np.linalg.inv(world[body.name])
    mass, moment = np.zeros(2), np.zeros((2, 3))  # [the subtree, the rest of the object]
    for piece, part_hulls in zip(obj.collision, hulls):
        side = 0 if piece.body in in_subtree else 1
        for vertices, faces in part_hulls:
            hull = trimesh.Trimesh(vertices, faces)
            centre = (to_body @ world[piece.body] @ np.append(hull.center_mass, 1.0))[:3]
            mass[side] += density * hull.volume
            moment[side] += density * hull.volume * centre
    weight = 9.81 * mass
    if body.joint.kind == "slide":
        load = weight.max()
    else:
        com = moment / np.maximum(mass, 1e-12)[:, None]
        axis = body.joint.axis
        load = (weight * np.linalg.norm(com - (com @ axis)[:, None] * axis, axis=1)).max()
    return max(physics.joint_frictionloss, physics.hold_factor * load)


def _next(counters: dict, part: str, tag: str) -> int:
    counters[(part, tag)] = counters.get((part, tag), -1) + 1
    return counters[(part, tag)]


def _obj_text(piece: MeshPiece) -> str:
    lines = [f"v {x:.6g} {y:.6g} {z:.6g}" for x, y, z in piece.vertices]
    if piece.uv is not None:
        lines += [f"vt {u:.6g} {v:.6g}" for u, v in piece.uv[:, :2]]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in piece.faces]
    else:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in piece.faces]
    return "\n".join(lines) + "\n"


def _num(value: float) -> str:
    return f"{float(value):.6g}"


def _vec(values) -> str:
    return " ".join(_num(v) for v in values)
