"""The procedural object library: every category builds valid, graspable, articulated objects in PartNet layout."""

from __future__ import annotations

import importlib.util
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from partinstruct_mjx.assets.naming import part_slug
from partinstruct_mjx.assets.partnet import is_semantic_label
from partinstruct_mjx.assets.procedural import CATEGORIES, build_object, generate

REPO = Path(__file__).resolve().parents[1]
INSTANCES = 8
WRITTEN_INSTANCES = 2
MOVING = {"revolute", "prismatic", "continuous"}
# Joint kinds each category must (at least) have; None = must be rigid.
ARTICULATION = {
    "scissors": {"revolute"}, "kitchen_pot": {"prismatic"}, "laptop": {"revolute"}, "eyeglasses": {"revolute"},
    "bucket": {"revolute"}, "display": None, "pliers": {"revolute"}, "bottle": None, "knife": set(),
    "stapler": {"revolute"}, "kettle": set(), "mug": None, "box": {"revolute"}, "dispenser": {"prismatic"},
}
HOLLOW = {"mug": ("body", "handle"), "kitchen_pot": ("base body",), "bucket": ("base body", "handle"),
          "box": ("base body",), "kettle": ("handle",)}


@pytest.fixture(scope="module")
def specs():
    return {slug: [build_object(slug, i, seed=0) for i in range(INSTANCES)] for slug in CATEGORIES}


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    root = tmp_path_factory.mktemp("builtin")
    return root, generate(root, seed=0, instances=WRITTEN_INSTANCES)


def _leaves(node: dict) -> list[dict]:
    children = node.get("children") or []
    return [node] if not children else [leaf for c in children for leaf in _leaves(c)]


def _origin(element: ET.Element | None) -> np.ndarray:
    found = None if element is None else element.find("origin")
    return np.zeros(3) if found is None else np.array([float(v) for v in found.get("xyz", "0 0 0").split()])


def _link_poses(urdf: ET.Element, q: dict[str, float]) -> dict[str, np.ndarray]:
    """World 4x4 pose of every link for joint values `q` (default 0), following URDF semantics."""
    poses = {"base": np.eye(4)}
    joints = urdf.findall("joint")
    while len(poses) < len(joints) + 1:
        for joint in joints:
            parent, child = joint.find("parent").get("link"), joint.find("child").get("link")
            if parent not in poses or child in poses:
                continue
            local = np.eye(4)
            local[:3, 3] = _origin(joint)
            rpy = joint.find("origin").get("rpy")
            if rpy:
                local[:3, :3] = Rotation.from_euler("xyz", [float(v) for v in rpy.split()]).as_matrix()
            motion = np.eye(4)
            value = q.get(joint.get("name"), 0.0)
            if joint.get("type") in MOVING:
                axis = np.array([float(v) for v in joint.find("axis").get("xyz").split()])
                if joint.get("type") == "prismatic":
                    motion[:3, 3] = axis * value
                else:
                    motion[:3, :3] = Rotation.from_rotvec(axis * value).as_matrix()
            poses[child] = poses[parent] @ local @ motion
    return poses


def _world_points(folder: Path, urdf: ET.Element, q: dict[str, float]) -> dict[str, np.ndarray]:
    poses = _link_poses(urdf, q)
    points = {}
    for link in urdf.findall("link")[1:]:
        chunks = []
        for visual in link.findall("visual"):
            vertices = trimesh.load(folder / visual.find("geometry/mesh").get("filename"), force="mesh").vertices
            local = vertices + _origin(visual)
            chunks.append(local @ poses[link.get("name")][:3, :3].T + poses[link.get("name")][:3, 3])
        points[link.get("name")] = np.vstack(chunks)
    return points


def test_every_category_writes_its_folders(library):
    root, written = library
    assert sorted(p.name for p in root.iterdir()) == sorted(CATEGORIES)
    for slug in CATEGORIES:
        ids = sorted(p.name for p in (root / slug).iterdir())
        assert ids == [f"{slug}_{i:03d}" for i in range(WRITTEN_INSTANCES)]
    for spec, folder in written:
        names = {p.name for p in folder.iterdir()}
        assert {"meta.json", "mobility.urdf", "semantics.txt", "result.json", "mobility_v2.json",
                "textured_objs"} <= names
        meta = json.loads((folder / "meta.json").read_text())
        assert meta == {"model_cat": CATEGORIES[spec.category].model_cat, "model_id": folder.name,
                        "anno_id": folder.name, "version": "1", "source": "partinstruct-mjx procedural generator",
                        "seed": 0}


def test_folders_parse_and_every_mesh_is_a_closed_volume(library):
    _, written = library
    for _, folder in written:
        urdf = ET.parse(folder / "mobility.urdf").getroot()
        links = urdf.findall("link")
        assert links[0].get("name") == "base" and len(links[0]) == 0
        referenced = []
        for link in links[1:]:
            visuals, collisions = link.findall("visual"), link.findall("collision")
            assert visuals and len(visuals) == len(collisions)
            for visual, collision in zip(visuals, collisions, strict=True):
                name = visual.find("geometry/mesh").get("filename")
                assert collision.find("geometry/mesh").get("filename") == name
                assert np.array_equal(_origin(visual), _origin(collision))
                referenced.append(name)
        on_disk = sorted(f"textured_objs/{p.name}" for p in (folder / "textured_objs").glob("*.obj"))
        assert sorted(referenced) == on_disk, folder
        for name in referenced:
            obj = folder / name
            text = obj.read_text()
            mtl = obj.with_suffix(".mtl")
            assert f"mtllib {mtl.name}" in text and "Kd " in mtl.read_text()
            mesh = trimesh.load(obj, force="mesh")
            assert len(mesh.faces) > 0 and mesh.is_volume, f"{obj} is not a closed, consistently wound volume"
        root_joint = [j for j in urdf.findall("joint") if j.find("parent").get("link") == "base"]
        assert len(root_joint) == 1 and root_joint[0].get("type") == "fixed"
        assert root_joint[0].find("origin").get("rpy") == "1.570796326794897 0 -1.570796326794897"
        for joint in urdf.findall("joint"):
            if joint.get("type") in MOVING:
                axis = np.array([float(v) for v in joint.find("axis").get("xyz").split()])
                assert np.isclose(np.linalg.norm(axis), 1.0)
                limit = joint.find("limit")
                assert set(limit.attrib) == {"lower", "upper"}
                assert float(limit.get("lower")) < float(limit.get("upper"))


def test_result_semantics_mobility_and_urdf_agree(library):
    _, written = library
    for spec, folder in written:
        result = json.loads((folder / "result.json").read_text())
        assert len(result) == 1 and result[0]["id"] == 0 and result[0]["name"] == spec.category
        leaves = {leaf["id"]: leaf for leaf in _leaves(result[0])}
        stems = [stem for leaf in leaves.values() for stem in leaf["objs"]]
        assert len(stems) == len(set(stems)), "an OBJ belongs to two leaves"
        assert sorted(stems) == sorted(p.stem for p in (folder / "textured_objs").glob("*.obj"))
        stem_leaf = {stem: leaf for leaf in leaves.values() for stem in leaf["objs"]}

        urdf = ET.parse(folder / "mobility.urdf").getroot()
        links = [ln for ln in urdf.findall("link") if ln.get("name") != "base"]
        semantics = (folder / "semantics.txt").read_text().splitlines()
        mobility = json.loads((folder / "mobility_v2.json").read_text())
        assert len(semantics) == len(links) == len(mobility) == len(spec.links)
        joint_of = {j.find("child").get("link"): j for j in urdf.findall("joint")}
        for index, (link, line, entry) in enumerate(zip(links, semantics, mobility, strict=True)):
            assert link.get("name") == f"link_{index}" and entry["id"] == index
            link_leaf_ids = set()
            for visual in link.findall("visual"):
                stem = Path(visual.find("geometry/mesh").get("filename")).stem
                leaf = stem_leaf[stem]
                assert visual.get("name") == f"{leaf['name']}-{leaf['id']}"
                link_leaf_ids.add(leaf["id"])
            assert {p["id"] for p in entry["parts"]} == link_leaf_ids
            assert all(p["name"] == leaves[p["id"]]["name"] for p in entry["parts"])
            name, word, label = line.split()
            joint = joint_of[f"link_{index}"]
            parent = joint.find("parent").get("link")
            expected = "free" if parent == "base" else {"revolute": "hinge", "continuous": "hinge",
                                                         "prismatic": "slider", "fixed": "static"}[joint.get("type")]
            assert (name, word) == (f"link_{index}", expected) and entry["joint"] == word
            assert label == entry["name"] and label in {leaves[i]["name"] for i in link_leaf_ids}
            assert entry["parent"] == (-1 if parent == "base" else int(parent.split("_")[1]))
            if word in ("hinge", "slider"):
                data = entry["jointData"]
                axis = np.array([float(v) for v in joint.find("axis").get("xyz").split()])
                assert np.allclose(data["axis"]["direction"], axis, atol=1e-5)
                lower, upper = (float(joint.find("limit").get(k)) for k in ("lower", "upper"))
                factor = np.degrees(1.0) if word == "hinge" else 1.0
                assert np.allclose([data["limit"]["a"], data["limit"]["b"]], [lower * factor, upper * factor],
                                   atol=1e-3)
            else:
                assert entry["jointData"] == {}


def test_part_labels_compositions_and_articulation(specs):
    for slug, instances in specs.items():
        allowed = {part_slug(p) for p in CATEGORIES[slug].parts}
        compositions = set()
        for spec in instances:
            labels = {part_slug(p) for p in spec.labels() if is_semantic_label(p)}  # 'other' leaves are free
            assert labels <= allowed, (spec.object_id, labels - allowed)
            compositions.add(frozenset(labels))
            kinds = {link.joint.kind for link in spec.links[1:]}
            moving = kinds & MOVING
            if ARTICULATION[slug] is None:
                assert not moving, spec.object_id
            else:
                assert ARTICULATION[slug] <= kinds, spec.object_id
        used = set().union(*compositions)
        assert used == allowed, f"{slug} never uses {allowed - used}"
    assert all("body" in {p.label for ln in s.links for p in ln.parts} for s in specs["bottle"])
    assert len({frozenset(s.labels()) for s in specs["bottle"]}) >= 3
    assert all(s.labels() & {"head", "pressing lid"} and "base body" in s.labels() for s in specs["dispenser"])
    assert all(len(s.links) == 3 for s in specs["eyeglasses"])
    assert all(any(ln.joint and ln.joint.kind in MOVING for ln in s.links) for s in specs["knife"])


def test_meshes_are_valid_and_moderate(specs):
    for instances in specs.values():
        for spec in instances:
            for link in spec.links:
                for part in link.parts:
                    assert sum(len(p.mesh.faces) for p in part.pieces) <= 3000, (spec.object_id, part.label)
                    for piece in part.pieces:
                        mesh = piece.mesh
                        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
                        assert mesh.area_faces.min() > 1e-10, (spec.object_id, part.label)


def test_sizes_are_table_top_and_graspable(specs):
    for slug, instances in specs.items():
        for spec in instances:
            extent = np.diff(spec.bounds(), axis=0)[0]
            assert 0.08 <= extent.max() <= 0.30, (spec.object_id, extent)
            for link in spec.links:
                for part in link.parts:
                    if part.label in CATEGORIES[slug].graspable:
                        points = np.vstack([p.mesh.vertices for p in part.pieces])
                        thinnest = trimesh.bounds.oriented_bounds(points)[1].min()
                        assert thinnest <= 0.07, (spec.object_id, part.label, thinnest)
    for spec in specs["bottle"]:
        extent = np.diff(spec.bounds(), axis=0)[0]
        assert 0.15 <= extent[2] <= 0.30 and 0.05 <= extent[:2].max() <= 0.07, (spec.object_id, extent)
    for spec in specs["mug"]:
        extent = np.diff(spec.bounds(), axis=0)[0]
        body = spec.links[0].parts[0].pieces[0].mesh.extents
        assert 0.08 <= extent[2] <= 0.12 and 0.06 <= body[:2].max() <= 0.09, (spec.object_id, extent)


def test_vessels_and_handles_are_hollow(specs):
    for slug, labels in HOLLOW.items():
        for spec in specs[slug]:
            for part in (p for ln in spec.links for p in ln.parts if p.label in labels):
                mesh = trimesh.util.concatenate([p.mesh for p in part.pieces])
                assert mesh.volume < 0.5 * mesh.convex_hull.volume, (spec.object_id, part.label)


def test_urdf_assembles_z_up_and_joints_move_sensibly(library):
    _, written = library
    for spec, folder in written:
        urdf = ET.parse(folder / "mobility.urdf").getroot()
        rest = _world_points(folder, urdf, {})
        everything = np.vstack(list(rest.values()))
        # Z-up after the root rotation, centred, and the same shape as designed.
        assert np.allclose(np.ptp(everything, axis=0), np.diff(spec.bounds(), axis=0)[0], atol=2e-6)
        assert np.allclose(everything.min(axis=0) + everything.max(axis=0), 0.0, atol=2e-6)
        floor = everything[:, 2].min()
        poses = _link_poses(urdf, {})
        for joint in urdf.findall("joint"):
            child, parent = joint.find("child").get("link"), joint.find("parent").get("link")
            if parent == "base":
                continue
            hinge = poses[child][:3, 3]
            for link in (child, parent):
                low, high = rest[link].min(axis=0) - 0.01, rest[link].max(axis=0) + 0.01
                assert np.all((low <= hinge) & (hinge <= high)), (folder.name, joint.get("name"), link)
            if joint.get("type") not in MOVING:
                continue
            for key in ("lower", "upper"):
                value = float(joint.find("limit").get(key))
                moved = _world_points(folder, urdf, {joint.get("name"): value})
                assert moved[child][:, 2].min() >= floor - 0.003, (folder.name, joint.get("name"), key)
        if spec.category == "laptop":  # closing the lid lays the screen flat on the base
            lower = float(urdf.find("joint[@name='joint_1']/limit").get("lower"))
            closed = _world_points(folder, urdf, {"joint_1": lower})["link_1"]
            assert np.ptp(closed[:, 2]) < 0.012


def test_same_seed_same_bytes_other_seed_other_geometry(tmp_path):
    def snapshot(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    for name, seed in (("a", 0), ("b", 0), ("c", 1)):
        generate(tmp_path / name, seed=seed, instances=1)
    first, second, other = (snapshot(tmp_path / name) for name in "abc")
    assert first == second
    for slug in CATEGORIES:
        name = f"{slug}/{slug}_000/textured_objs/original-1.obj"
        assert other[name] != first[name], slug


def test_subset_matches_full_run_and_bad_arguments_are_named(tmp_path):
    subset = build_object("mug", 3, seed=5)
    assert subset.object_id == "mug_003"
    again = build_object("mug", 3, seed=5)
    assert np.array_equal(subset.links[0].parts[0].pieces[0].mesh.vertices,
                          again.links[0].parts[0].pieces[0].mesh.vertices)
    with pytest.raises(ValueError, match="'teapot'"):
        build_object("teapot", 0)
    with pytest.raises(ValueError, match="'spoon'"):
        generate(tmp_path, categories=["mug", "spoon"])
    assert not any(tmp_path.iterdir())
    with pytest.raises(ValueError, match="non-negative"):
        build_object("mug", 0, seed=-1)
    with pytest.raises(ValueError, match="at least 1"):
        generate(tmp_path, instances=0)


def test_cli_builds_the_requested_subset(tmp_path, capsys):
    """The one-command build: PartNet-format sources, converted objects, a catalog with splits."""
    loader = importlib.util.spec_from_file_location("make_builtin_objects", REPO / "tools" / "make_builtin_objects.py")
    cli = importlib.util.module_from_spec(loader)
    loader.loader.exec_module(cli)
    sources, assets = tmp_path / "src", tmp_path / "assets"
    arguments = ["--out", str(assets), "--sources", str(sources), "--preset", "fast", "--sheet", "-", "--report", "-",
                 "--instances", "1", "--categories", "box", "mug"]
    assert cli.main(arguments) == 0
    assert sorted(p.name for p in sources.iterdir()) == ["box", "mug"]
    assert (sources / "mug" / "mug_000" / "mobility.urdf").is_file()
    assert (assets / "objects" / "mug" / "mug_000" / "object.xml").is_file()
    catalog = json.loads((assets / "catalog.json").read_text())["objects"]
    assert sorted(e["id"] for e in catalog) == ["box_000", "mug_000"] and all(e["splits"] for e in catalog)
    assert "2 converted" in capsys.readouterr().out
    with pytest.raises(SystemExit) as failure:
        cli.main(["--out", str(assets), "--sources", str(sources), "--categories", "spoon"])
    assert failure.value.code == 2 and "'spoon'" in capsys.readouterr().err
