"""Reading one PartNet-Mobility object folder: URDF kinematics, part hierarchy, semantics, metadata.

Real quirks are handled, not rejected: non-unit joint axes, `-0.0` limits, missing effort/velocity, repeated visual
names, stale `<limit>` on fixed joints, `*_helper` links of screw joints. Malformed input raises AssetError naming
the file and the element.
"""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from partinstruct_mjx.errors import AssetError

JOINT_TYPES = ("fixed", "revolute", "prismatic", "continuous")
HIERARCHY_FILES = ("result_after_merging.json", "result.json")


@dataclass(frozen=True)
class Visual:
    """One `<visual>` mesh of a link: the OBJ, its pose in the link frame and its `<mesh scale>`."""

    mesh: Path
    transform: np.ndarray
    scale: np.ndarray

    @property
    def stem(self) -> str:
        return self.mesh.stem


@dataclass(frozen=True)
class Joint:
    name: str
    type: str
    parent: str
    child: str
    transform: np.ndarray
    """Child link frame in the parent link frame (the joint's `<origin>`)."""
    axis: np.ndarray
    """Unit axis in the child frame."""
    limits: tuple[float, float] | None


@dataclass(frozen=True)
class PartNetObject:
    folder: Path
    object_id: str
    category: str
    """`meta.json` model_cat, e.g. 'KitchenPot'."""
    root_link: str
    links: dict[str, tuple[Visual, ...]]
    joints: tuple[Joint, ...]
    mesh_labels: dict[str, str]
    """Mesh stem -> fine part label (leaf name of the hierarchy, lower case, spaces for underscores)."""
    semantics: dict[str, tuple[str, str]]
    """Link name -> (joint word, label) from semantics.txt."""
    source_files: tuple[Path, ...]
    """Every file the conversion reads, for the content hash."""


def category_slug(category: str) -> str:
    """'KitchenPot' -> 'kitchen_pot', 'kitchen pot' -> 'kitchen_pot'."""
    spaced = re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", category.strip())
    return re.sub(r"[\s_]+", "_", spaced).lower()


def part_label(name: str) -> str:
    """PartNet leaf name -> part label of the original (spec 3.2): lower case, underscores become spaces."""
    return name.strip().lower().replace("_", " ")


def is_semantic_label(label: str) -> bool:
    """The original skips leaves whose name contains 'other' (spec 3.2)."""
    return "other" not in label


def read_partnet_object(folder: str | Path) -> PartNetObject:
    """Read and validate a PartNet-Mobility object folder; raises AssetError naming the file that is wrong."""
    folder = Path(folder).resolve()
    if not folder.is_dir():
        raise AssetError(f"not a PartNet-Mobility object folder: {folder}")
    meta = _read_json(folder / "meta.json")
    category = meta.get("model_cat") if isinstance(meta, dict) else None
    if not category:
        raise AssetError(f"{folder / 'meta.json'}: missing 'model_cat'")
    hierarchy_file = next((folder / n for n in HIERARCHY_FILES if (folder / n).is_file()), None)
    if hierarchy_file is None:
        raise AssetError(f"{folder}: neither {' nor '.join(HIERARCHY_FILES)} exists")
    mesh_labels = _leaf_labels(_read_json(hierarchy_file), hierarchy_file)
    semantics = _read_semantics(folder / "semantics.txt")
    if (folder / "mobility_v2.json").is_file():
        _read_json(folder / "mobility_v2.json")
    urdf = folder / "mobility.urdf"
    links, joints = _read_urdf(urdf, folder)
    children = {j.child for j in joints}
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise AssetError(f"{urdf}: expected one root link, found {roots or 'none'}")
    for link, visuals in links.items():
        for visual in visuals:
            if visual.stem not in mesh_labels:
                raise AssetError(f"{hierarchy_file}: mesh '{visual.stem}' of link '{link}' is in no leaf part")
    used = {v.stem for visuals in links.values() for v in visuals}
    for label in sorted(set(mesh_labels.values())):
        stems = [s for s, lab in mesh_labels.items() if lab == label]
        if is_semantic_label(label) and not used.intersection(stems):
            raise AssetError(f"{hierarchy_file}: part '{label}' has no geometry in {urdf.name} "
                             f"(meshes {', '.join(sorted(stems)) or 'none'})")
    meshes = sorted({v.mesh for visuals in links.values() for v in visuals})
    mtls = sorted(p for p in (m.with_suffix(".mtl") for m in meshes) if p.is_file())
    return PartNetObject(
        folder=folder,
        object_id=folder.name,
        category=str(category),
        root_link=roots[0],
        links=links,
        joints=tuple(joints),
        mesh_labels=mesh_labels,
        semantics=semantics,
        source_files=(urdf, folder / "meta.json", hierarchy_file, folder / "semantics.txt", *meshes, *mtls),
    )


def _read_json(path: Path):
    if not path.is_file():
        raise AssetError(f"missing file: {path}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise AssetError(f"{path}: not valid JSON ({err})") from err


def _leaf_labels(hierarchy, path: Path) -> dict[str, str]:
    if not isinstance(hierarchy, list) or not hierarchy or not isinstance(hierarchy[0], dict):
        raise AssetError(f"{path}: expected a list of part nodes")
    labels: dict[str, str] = {}

    def walk(node):
        if not isinstance(node, dict) or "name" not in node:
            raise AssetError(f"{path}: a node without 'name'")
        children = node.get("children") or []
        if not children:
            for stem in node.get("objs") or []:
                labels[str(stem)] = part_label(node["name"])
        for child in children:
            walk(child)

    for node in hierarchy:
        walk(node)
    if not labels:
        raise AssetError(f"{path}: no leaf part lists any mesh")
    return labels


def _read_semantics(path: Path) -> dict[str, tuple[str, str]]:
    if not path.is_file():
        raise AssetError(f"missing file: {path} (part semantics are required)")
    semantics = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        fields = line.split()
        if len(fields) != 3:
            raise AssetError(f"{path}:{number}: expected 'link_N <joint type> <label>', got '{line.strip()}'")
        semantics[fields[0]] = (fields[1], part_label(fields[2]))
    if not semantics:
        raise AssetError(f"{path}: empty")
    return semantics


def _floats(element: ET.Element | None, attribute: str, default: list[float], where: str) -> np.ndarray:
    if element is None or element.get(attribute) is None:
        return np.array(default, dtype=float)
    text = element.get(attribute)
    try:
        values = np.array([float(v) for v in text.split()], dtype=float)
    except ValueError:
        raise AssetError(f"{where} <{element.tag} {attribute}>: cannot read '{text}' as numbers") from None
    if values.shape != (len(default),) or not np.isfinite(values).all():
        raise AssetError(f"{where} <{element.tag} {attribute}>: expected {len(default)} finite numbers, got '{text}'")
    return values


def _origin(element: ET.Element, where: str) -> np.ndarray:
    origin = element.find("origin")
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_euler("xyz", _floats(origin, "rpy", [0, 0, 0], where)).as_matrix()
    transform[:3, 3] = _floats(origin, "xyz", [0, 0, 0], where)
    return transform


def _read_urdf(urdf: Path, folder: Path) -> tuple[dict[str, tuple[Visual, ...]], list[Joint]]:
    if not urdf.is_file():
        raise AssetError(f"missing file: {urdf}")
    try:
        robot = ET.parse(urdf).getroot()
    except ET.ParseError as err:
        raise AssetError(f"{urdf}: malformed XML ({err})") from err
    links: dict[str, tuple[Visual, ...]] = {}
    for link in robot.findall("link"):
        name = link.get("name")
        if not name:
            raise AssetError(f"{urdf}: a <link> without a name")
        visuals = []
        for index, visual in enumerate(link.findall("visual")):
            where = f"{urdf}: link '{name}' visual #{index}"
            mesh = visual.find("geometry/mesh")
            if mesh is None or not mesh.get("filename"):
                raise AssetError(f"{where}: only <mesh filename=...> geometry is supported")
            path = (folder / mesh.get("filename")).resolve()
            if not path.is_file():
                raise AssetError(f"{where}: mesh file not found: {path}")
            visuals.append(Visual(path, _origin(visual, where), _floats(mesh, "scale", [1, 1, 1], where)))
        links[name] = tuple(visuals)
    joints = []
    for joint in robot.findall("joint"):
        name = joint.get("name", "?")
        where = f"{urdf}: joint '{name}'"
        kind = joint.get("type")
        if kind not in JOINT_TYPES:
            raise AssetError(f"{where}: unsupported type '{kind}' (supported: {', '.join(JOINT_TYPES)})")
        parent, child = joint.find("parent"), joint.find("child")
        if parent is None or child is None or parent.get("link") not in links or child.get("link") not in links:
            raise AssetError(f"{where}: parent/child must name links of the file")
        axis = _floats(joint.find("axis"), "xyz", [1, 0, 0], where)
        if kind != "fixed":
            norm = np.linalg.norm(axis)
            if norm < 1e-9:
                raise AssetError(f"{where}: zero-length <axis>")
            axis = axis / norm
        limits = None
        if kind in ("revolute", "prismatic"):
            limit = joint.find("limit")
            if limit is None:
                raise AssetError(f"{where}: a {kind} joint needs <limit lower upper>")
            lower = _floats(limit, "lower", [0.0], where)[0] + 0.0  # + 0.0 turns -0.0 into 0.0
            upper = _floats(limit, "upper", [0.0], where)[0] + 0.0
            if lower > upper:
                raise AssetError(f"{where}: <limit> lower {lower} > upper {upper}")
            limits = (lower, upper)
        joints.append(Joint(name, kind, parent.get("link"), child.get("link"), _origin(joint, where), axis, limits))
    if not links:
        raise AssetError(f"{urdf}: no <link> elements")
    return links, joints
