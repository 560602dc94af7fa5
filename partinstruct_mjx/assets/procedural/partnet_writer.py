"""Write an `ObjectSpec` as a PartNet-Mobility object folder.

Layout: meta.json, mobility.urdf, semantics.txt, result.json, mobility_v2.json, textured_objs/original-<k>.obj/.mtl.
As in the dataset, OBJ files are Y-up and centred on the object's bounding box, and the URDF's fixed root joint
rotates them Z-up with rpy = (pi/2, 0, -pi/2). Unlike the dataset, OBJ units are metres at real size (scale 1).
Output is byte-deterministic: fixed float formatting, no timestamps.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from partinstruct_mjx.assets.naming import part_slug
from partinstruct_mjx.assets.procedural.spec import Joint, ObjectSpec

ROOT_RPY = "1.570796326794897 0 -1.570796326794897"
# world = OBJ_TO_DESIGN @ obj for the root rpy above (URDF fixed-axis roll-pitch-yaw).
OBJ_TO_DESIGN = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
SOURCE = "partinstruct-mjx procedural generator"
JOINT_WORDS = {None: "free", "revolute": "hinge", "prismatic": "slider", "fixed": "static"}


def _num(x: float) -> str:
    """Fixed six-decimal number without trailing zeros or negative zero."""
    text = f"{float(x):.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _vec(v: np.ndarray) -> str:
    return " ".join(_num(x) for x in v)


def _rounded(v: np.ndarray | list[float], digits: int = 6) -> list[float]:
    return [round(float(x), digits) + 0.0 for x in v]


def _obj_text(stem: str, vertices: np.ndarray, faces: np.ndarray) -> str:
    v = np.round(vertices, 6) + 0.0
    lines = [f"# {SOURCE}", f"mtllib {stem}.mtl", f"o {stem}", "usemtl material_0"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v]
    lines += [f"f {a} {b} {c}" for a, b, c in faces + 1]
    return "\n".join(lines) + "\n"


def _mtl_text(rgb: tuple[float, float, float]) -> str:
    r, g, b = (f"{c:.4f}" for c in rgb)
    return f"newmtl material_0\nKa 0 0 0\nKd {r} {g} {b}\nKs 0.0667 0.0667 0.0667\nNs 30\nd 1\nillum 2\n"


def _joint_data(joint: Joint | None, anchor: np.ndarray) -> dict:
    if joint is None or joint.kind == "fixed":
        return {}
    axis = OBJ_TO_DESIGN.T @ np.asarray(joint.axis)
    if joint.kind == "revolute":  # hinge limits in degrees, slider limits in metres, as in the dataset
        a, b = _rounded(np.degrees([joint.lower, joint.upper]), 4)
    else:
        a, b = _rounded([joint.lower, joint.upper])
    return {"axis": {"origin": _rounded(anchor), "direction": _rounded(axis)},
            "limit": {"a": a, "b": b, "noLimit": False}}


def write_partnet(spec: ObjectSpec, folder: Path) -> Path:
    """Write `spec` into `folder` (replaced if it exists) and return the folder."""
    folder = Path(folder)
    if folder.exists():
        shutil.rmtree(folder)
    objs_dir = folder / "textured_objs"
    objs_dir.mkdir(parents=True)

    centre = spec.bounds().mean(axis=0)

    def to_obj(points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=float) - centre) @ OBJ_TO_DESIGN

    anchors = [np.zeros(3) if ln.joint is None else to_obj(ln.joint.origin) for ln in spec.links]
    root = {"id": 0, "text": spec.model_cat, "name": spec.category, "objs": [], "children": []}
    next_id, obj_count = 1, 0
    urdf = [f'<?xml version="1.0" ?>\n<robot name="partnet_{spec.object_id}">', '\t<link name="base"/>']
    semantics, mobility = [], []
    for index, link in enumerate(spec.links):
        groups: dict[str, dict] = {}
        leaf_refs, visuals, collisions = [], [], []
        origin = f'\t\t\t<origin xyz="{_vec(-anchors[index])}"/>\n'
        for part in link.parts:
            parent_node = root
            if part.group is not None:
                if part.group not in groups:
                    groups[part.group] = {"id": next_id, "text": part.group.replace("_", " "),
                                          "name": part.group, "children": []}
                    root["children"].append(groups[part.group])
                    next_id += 1
                parent_node = groups[part.group]
            leaf = {"id": next_id, "text": part.label, "name": part_slug(part.label), "objs": []}
            next_id += 1
            parent_node["children"].append(leaf)
            leaf_refs.append({"id": leaf["id"], "name": leaf["name"], "children": []})
            for piece in part.pieces:
                obj_count += 1
                stem = f"original-{obj_count}"
                leaf["objs"].append(stem)
                (objs_dir / f"{stem}.obj").write_text(
                    _obj_text(stem, to_obj(piece.mesh.vertices), np.asarray(piece.mesh.faces)))
                (objs_dir / f"{stem}.mtl").write_text(_mtl_text(piece.rgb))
                mesh = f'\t\t\t<geometry>\n\t\t\t\t<mesh filename="textured_objs/{stem}.obj"/>\n\t\t\t</geometry>\n'
                visuals.append(f'\t\t<visual name="{leaf["name"]}-{leaf["id"]}">\n{origin}{mesh}\t\t</visual>')
                collisions.append(f"\t\t<collision>\n{origin}{mesh}\t\t</collision>")
        urdf.append(f'\t<link name="link_{index}">\n' + "\n".join(visuals + collisions) + "\n\t</link>")
        urdf.append(_urdf_joint(index, link.joint, anchors))
        word = JOINT_WORDS[None if link.joint is None else link.joint.kind]
        semantics.append(f"link_{index} {word} {part_slug(link.label)}")
        mobility.append({"id": index, "parent": -1 if link.joint is None else link.joint.parent, "joint": word,
                         "name": part_slug(link.label), "parts": leaf_refs,
                         "jointData": _joint_data(link.joint, anchors[index])})
    urdf.append("</robot>")

    meta = {"model_cat": spec.model_cat, "model_id": spec.object_id, "anno_id": spec.object_id, "version": "1",
            "source": SOURCE, "seed": spec.seed}
    (folder / "mobility.urdf").write_text("\n".join(urdf) + "\n")
    (folder / "semantics.txt").write_text("\n".join(semantics) + "\n")
    (folder / "result.json").write_text(json.dumps([root]))
    (folder / "mobility_v2.json").write_text(json.dumps(mobility))
    (folder / "meta.json").write_text(json.dumps(meta))
    return folder


def _urdf_joint(index: int, joint: Joint | None, anchors: list[np.ndarray]) -> str:
    head = f'\t<joint name="joint_{index}" type="{"fixed" if joint is None else joint.kind}">\n'
    if joint is None:
        return (head + f'\t\t<origin rpy="{ROOT_RPY}" xyz="0 0 0"/>\n\t\t<child link="link_{index}"/>\n'
                '\t\t<parent link="base"/>\n\t</joint>')
    body = f'\t\t<origin xyz="{_vec(anchors[index] - anchors[joint.parent])}"/>\n'
    if joint.kind != "fixed":
        body += f'\t\t<axis xyz="{_vec(OBJ_TO_DESIGN.T @ np.asarray(joint.axis))}"/>\n'
    body += f'\t\t<child link="link_{index}"/>\n\t\t<parent link="link_{joint.parent}"/>\n'
    if joint.kind != "fixed":
        body += f'\t\t<limit lower="{_num(joint.lower)}" upper="{_num(joint.upper)}"/>\n'
    return head + body + "\t</joint>"
