"""The PartNet-Mobility converter on the six real samples in ../shared/partnet_samples, and on broken copies."""

import json
import math
import os
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
import trimesh

from partinstruct_mjx.assets.convert import ConvertConfig, convert_objects, summary_table
from partinstruct_mjx.assets.decompose import DecompositionConfig, _convex, hull_budgets
from partinstruct_mjx.assets.geometry import assemble
from partinstruct_mjx.assets.partnet import is_semantic_label, part_label, read_partnet_object
from partinstruct_mjx.assets.timeout_pool import run_jobs
from partinstruct_mjx.errors import AssetError
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
from partinstruct_mjx.sim.scene import SceneConfig, build_scene

REPO = Path(__file__).resolve().parents[1]
SAMPLES = Path(os.environ.get("PARTINSTRUCT_SAMPLES", REPO.parent / "shared" / "partnet_samples"))
SAMPLE_IDS = ["100015", "100454", "102456", "10280", "103619", "11100"]
pytestmark = pytest.mark.skipif(not SAMPLES.is_dir(), reason=f"PartNet-Mobility samples not found at {SAMPLES}")


def _fast_config(cache: Path, **changes) -> ConvertConfig:
    return replace(ConvertConfig(decomposition=DecompositionConfig.fast(), cache_dir=str(cache)), **changes)


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    """All six samples converted once with the fast CoACD preset."""
    out, cache = tmp_path_factory.mktemp("assets"), tmp_path_factory.mktemp("cache")
    config = _fast_config(cache)
    records = convert_objects([SAMPLES], out, config, progress=False)
    return out, {r.object_id: r for r in records}, config


@pytest.fixture()
def bucket_copy(tmp_path):
    """A writable copy of the smallest sample (bucket 100454) to break."""
    return Path(shutil.copytree(SAMPLES / "100454", tmp_path / "src" / "100454"))


def _leaf_labels(folder: Path) -> set[str]:
    name = "result_after_merging.json" if (folder / "result_after_merging.json").exists() else "result.json"
    labels = set()

    def walk(node):
        if not node.get("children") and node.get("objs"):
            labels.add(part_label(node["name"]))
        for child in node.get("children", []):
            walk(child)

    for node in json.loads((folder / name).read_text()):
        walk(node)
    return {label for label in labels if is_semantic_label(label)}


def test_all_samples_convert_with_complete_outputs(converted):
    out, records, _ = converted
    assert sorted(records) == sorted(SAMPLE_IDS)
    assert all(r.status == "converted" for r in records.values()), summary_table(list(records.values()))
    catalog = json.loads((out / "catalog.json").read_text())["objects"]
    assert sorted(e["id"] for e in catalog) == sorted(SAMPLE_IDS)
    for record in records.values():
        for name in ("object.xml", "parts.npz", "meta.json", "meshes"):
            assert (record.output / name).exists()
    assert not list(out.rglob(".*tmp*")) and not list(out.rglob(".*old*"))


def test_part_labels_match_the_dataset_annotation(converted):
    out, records, _ = converted
    for object_id, record in records.items():
        meta = json.loads((record.output / "meta.json").read_text())
        semantic = {p["name"] for p in meta["parts"] if p["semantic"]}
        assert semantic == _leaf_labels(SAMPLES / object_id), object_id
        parts = np.load(record.output / "parts.npz")
        assert set(parts["part_names"]) == semantic
        scene = build_scene(SceneConfig(object_xml=str(record.output / "object.xml")))
        assert semantic <= set(scene.part_names)
    assert {p["name"] for p in json.loads((records["103619"].output / "meta.json").read_text())["parts"]} >= \
        {"handle", "head", "base body"}


def test_objects_load_in_mjx_and_settle_on_the_table(converted):
    from mujoco import mjx

    _, records, _ = converted
    for object_id, record in records.items():
        scene = build_scene(SceneConfig(object_xml=str(record.output / "object.xml")))
        mjx.put_model(scene.model)
        with MujocoBackend(scene, 1) as backend:
            settled = backend.reset()
            for _ in range(40):
                state = backend.step(panda.HOME_CTRL[None])
        adr = scene.object_qpos_adr
        assert np.abs(state.object_pos - settled.object_pos).max() < 1e-3, object_id
        assert np.abs(state.qpos[0, adr + 7:] - settled.qpos[0, adr + 7:]).max(initial=0) < 0.01, object_id
        # The pose, not the velocity: a pot resting on several hulls chatters at up to 0.2 rad/s in place.
        turned = 2 * np.arccos(min(1.0, abs(float(state.object_quat[0] @ settled.object_quat[0]))))
        assert turned < 0.01, object_id
        depths = backend.datas[0].contact.dist[: backend.datas[0].ncon]
        assert depths.min(initial=0.0) > -2e-3, object_id


def test_budgets_and_mass(converted):
    _, records, config = converted
    budget = config.decomposition
    for object_id, record in records.items():
        meta = json.loads((record.output / "meta.json").read_text())
        assert meta["stats"]["hulls"] <= budget.max_hulls_per_object
        assert all(p["hulls"] <= budget.max_hulls_per_part for p in meta["parts"])
        for stl in (record.output / "meshes").glob("col_*.stl"):
            assert len(trimesh.load(stl).vertices) <= budget.max_hull_vertices
        model = mujoco.MjModel.from_xml_path(str(record.output / "object.xml"))
        assert model.body_subtreemass[1] == pytest.approx(config.physics.mass, rel=1e-3)


def test_parts_npz_points_lie_on_their_bodies(converted):
    _, records, config = converted
    for record in records.values():
        parts = np.load(record.output / "parts.npz")
        n_parts = len(parts["part_names"])
        assert parts["points"].shape == (n_parts, config.points_per_part, 3)
        assert parts["object_points"].shape == (config.object_points, 3)
        np.testing.assert_allclose(np.linalg.norm(parts["normals"], axis=-1), 1.0, atol=1e-4)
        assert parts["point_body"].max() < len(parts["body_names"])
        assert np.abs(parts["object_points"]).max() < config.target_size


def test_mesh_scale_attribute_and_target_size_are_honoured():
    obj = read_partnet_object(SAMPLES / "11100")  # every <mesh> has scale="0.2 0.2 0.2"
    raw = np.concatenate([trimesh.load(v.mesh, force="mesh").vertices for vs in obj.links.values() for v in vs])
    unit = assemble(obj, scale=1.0, target_size=None, rigid=True)
    points = np.concatenate([p.vertices for p in unit.collision])
    np.testing.assert_allclose(np.sort(np.ptp(points, axis=0)), np.sort(np.ptp(raw, axis=0) * 0.2), rtol=0.02)
    sized = assemble(obj, scale=None, target_size=0.15, rigid=True)
    assert np.ptp(np.concatenate([p.vertices for p in sized.collision]), axis=0).max() == pytest.approx(0.15)


def test_root_joint_rotation_makes_objects_z_up():
    """The bucket's OBJs are Y-up; after the root joint's rpy its opening faces +z (handle above the body)."""
    obj = read_partnet_object(SAMPLES / "100454")
    assembled = assemble(obj, scale=None, target_size=0.2, rigid=True)
    heights = {p.part: p.vertices[:, 2].max() for p in assembled.collision}
    assert heights["handle"] > heights["base body"] - 1e-6


def test_dataset_quirks_are_handled(converted):
    laptop = read_partnet_object(SAMPLES / "10280")  # axis -0.98 0 0, upper limit -0.0
    (hinge,) = [j for j in laptop.joints if j.type == "revolute"]
    assert np.linalg.norm(hinge.axis) == pytest.approx(1.0)
    assert hinge.limits[1] == 0.0 and not math.copysign(1.0, hinge.limits[1]) < 0
    dispenser = read_partnet_object(SAMPLES / "103619")  # helper link, stale limit on a fixed joint, repeated names
    assert "link_2_helper" in dispenser.links
    assert sum(len(v) for v in dispenser.links.values()) == 11
    _, records, _ = converted
    meta = json.loads((records["103619"].output / "meta.json").read_text())
    assert [j["name"] for j in meta["joints"]] == ["joint_0"]  # the frozen screw chain merged into the body
    box_xml = (records["102456"].output / "object.xml").read_text()
    assert 'type="hinge"' in box_xml


def test_rerun_is_cached_and_a_setting_change_reconverts(tmp_path):
    config = _fast_config(tmp_path / "cache")
    first = convert_objects([SAMPLES / "100454"], tmp_path / "out", config, progress=False)
    start = time.perf_counter()
    second = convert_objects([SAMPLES / "100454"], tmp_path / "out", config, progress=False)
    assert [r.status for r in first] == ["converted"] and [r.status for r in second] == ["cached"]
    assert time.perf_counter() - start < 2.0
    third = convert_objects([SAMPLES / "100454"], tmp_path / "out", replace(config, points_per_part=256), progress=False)
    assert [r.status for r in third] == ["converted"]
    assert np.load(third[0].output / "parts.npz")["points"].shape[1] == 256


def test_an_mjcf_writer_change_reconverts(monkeypatch):
    # Changing what is written for the same hulls (convert.MJCF_VERSION) must change the hash that decides a rerun,
    # or objects converted before the change would be kept as cached.
    from partinstruct_mjx.assets import convert

    obj, config = read_partnet_object(SAMPLES / "100454"), ConvertConfig()
    before = convert.source_hash(obj, config)
    monkeypatch.setattr(convert, "MJCF_VERSION", convert.MJCF_VERSION + "-next")
    assert convert.source_hash(obj, config) != before


def test_rigid_option_freezes_every_joint(tmp_path):
    (record,) = convert_objects([SAMPLES / "100454"], tmp_path / "out", _fast_config(tmp_path / "c", rigid=True),
                                progress=False)
    model = mujoco.MjModel.from_xml_path(str(record.output / "object.xml"))
    assert model.njnt == 0 and model.nbody == 2


def test_timeout_fails_the_object_and_keeps_the_previous_output(tmp_path):
    config = _fast_config(tmp_path / "cache")
    (good,) = convert_objects([SAMPLES / "10280"], tmp_path / "out", config, progress=False)
    before = (good.output / "meta.json").read_text()
    slow = replace(config, decomposition=DecompositionConfig(), timeout=0.5)  # uncached, full-quality CoACD
    (record,) = convert_objects([SAMPLES / "10280"], tmp_path / "out", slow, progress=False)
    assert record.status == "failed" and "timed out after 0.5 s" in record.reason
    assert (good.output / "meta.json").read_text() == before
    assert sorted(p.name for p in good.output.parent.iterdir()) == ["10280"]


@pytest.mark.parametrize("breakage, message", [
    ("missing_mesh", "original-1.obj"),
    ("bad_number", "cannot read '0 abc 0' as numbers"),
    ("missing_semantics", "semantics.txt"),
    ("part_without_geometry", "part 'lid' has no geometry"),
    ("empty_mesh", "empty mesh (no faces)"),
    ("malformed_xml", "malformed XML"),
    ("unknown_joint_type", "unsupported type 'floating'"),
    ("missing_meta", "meta.json"),
])
def test_bad_input_gets_a_clear_error_and_no_output(bucket_copy, tmp_path, breakage, message):
    urdf = bucket_copy / "mobility.urdf"
    if breakage == "missing_mesh":
        (bucket_copy / "textured_objs" / "original-1.obj").unlink()
    elif breakage == "bad_number":
        urdf.write_text(urdf.read_text().replace('<origin xyz="0 0 0"', '<origin xyz="0 abc 0"', 1))
    elif breakage == "missing_semantics":
        (bucket_copy / "semantics.txt").unlink()
    elif breakage == "part_without_geometry":
        result = json.loads((bucket_copy / "result.json").read_text())
        result[0]["children"].append({"name": "lid", "objs": ["original-99"]})
        (bucket_copy / "result.json").write_text(json.dumps(result))
    elif breakage == "empty_mesh":
        (bucket_copy / "textured_objs" / "original-1.obj").write_text("v 0 0 0\nv 1 0 0\n")
    elif breakage == "malformed_xml":
        urdf.write_text(urdf.read_text()[:-20])
    elif breakage == "unknown_joint_type":
        urdf.write_text(urdf.read_text().replace('type="revolute"', 'type="floating"', 1))
    elif breakage == "missing_meta":
        (bucket_copy / "meta.json").unlink()
    if breakage != "empty_mesh":  # meshes are loaded when the object is assembled, not when it is read
        with pytest.raises(AssetError, match=message.replace("(", r"\(").replace(")", r"\)")):
            read_partnet_object(bucket_copy)
    (record,) = convert_objects([bucket_copy], tmp_path / "out", _fast_config(tmp_path / "cache"), progress=False)
    assert record.status == "failed" and message in record.reason
    if breakage == "empty_mesh":
        assert "original-1.obj" in record.reason
    assert not (tmp_path / "out" / "objects").exists()


def test_hull_budgets_stay_within_limits():
    config = DecompositionConfig(max_hulls_per_part=8, max_hulls_per_object=16)
    budgets = hull_budgets([10.0, 1.0, 0.01, 3.0], config)
    assert sum(budgets) <= 16 and min(budgets) >= 1 and max(budgets) <= 8 and budgets[0] == max(budgets)
    with pytest.raises(AssetError, match="17 collision parts exceed the budget of 16"):
        hull_budgets([1.0] * 17, config)


def test_reduced_hulls_keep_the_flat_base_they_stand_on():
    # The built-in bottle_000's body: one 482-vertex hull (CoACD keeps it whole), reduced to 32
    # vertices. Farthest points alone kept one vertex of its flat base, and the bottle fell over at every reset.
    from partinstruct_mjx.assets.procedural.generator import build_object

    spec = build_object("bottle", 0)
    (body,) = [part for link in spec.links for part in link.parts if part.label == "body"]
    vertices, _ = _convex(np.asarray(body.pieces[0].mesh.vertices), 32)
    assert len(vertices) <= 32
    base = vertices[vertices[:, 2] < vertices[:, 2].min() + 1e-4]
    assert len(base) >= 4 and min(np.ptp(base[:, 0]), np.ptp(base[:, 1])) > 0.02


def test_builtin_bottles_stand_upright():
    from partinstruct_mjx.paths import assets_root
    from partinstruct_mjx.tasks.slot_rules import settled_tilt

    for name in ("bottle_000", "bottle_007"):
        tilt = settled_tilt(assets_root() / "objects" / "bottle" / name / "object.xml")
        assert math.degrees(math.acos(min(1.0, tilt[2, 2]))) < 1.0, name


def test_timeout_pool_kills_slow_jobs_and_reports_errors():
    results = {r.key: r for r in run_jobs(time.sleep, [("slow", (30,)), ("quick", (0,))], workers=2, timeout=1.0)}
    assert results["slow"].error == "timed out after 1 s" and results["quick"].error is None
    (failed,) = run_jobs(math.sqrt, [("bad", (-1.0,))], workers=1, timeout=10)
    assert "ValueError" in failed.error


def test_convert_command_line_help_and_tool_wrapper():
    for command in ([sys.executable, "-m", "partinstruct_mjx.cli", "convert", "--help"],
                    [sys.executable, str(REPO / "tools" / "convert_partnet.py"), "--help"]):
        out = subprocess.run(command, capture_output=True, text=True)
        assert out.returncode == 0 and "--target-size" in out.stdout and "--rigid" in out.stdout


def test_screw_chain_and_continuous_joints_become_moving_bodies(tmp_path):
    """A screw (`slider+`) is a prismatic joint to a `*_helper` link plus a continuous joint; both must move."""
    folder = Path(shutil.copytree(SAMPLES / "103619", tmp_path / "src" / "103619"))
    urdf = folder / "mobility.urdf"
    text = urdf.read_text()
    text = text.replace('<joint name="joint_3" type="fixed">', '<joint name="joint_3" type="prismatic">')
    text = text.replace('<joint name="joint_2" type="fixed">', '<joint name="joint_2" type="continuous">')
    urdf.write_text(text)
    (record,) = convert_objects([folder], tmp_path / "out", _fast_config(tmp_path / "cache"), progress=False)
    assert record.status == "converted", record.reason
    model = mujoco.MjModel.from_xml_path(str(record.output / "object.xml"))
    slide, hinge = model.joint("joint_3"), model.joint("joint_2")
    assert slide.type == mujoco.mjtJoint.mjJNT_SLIDE and slide.limited
    assert hinge.type == mujoco.mjtJoint.mjJNT_HINGE and not hinge.limited
    assert model.body("link_2_helper").mass[0] > 0 and model.body("link_2").mass[0] > 0


def test_unreadable_mesh_is_named(bucket_copy, tmp_path):
    (bucket_copy / "textured_objs" / "original-1.obj").write_bytes(b"\x00\xff garbage \x01" * 50)
    (record,) = convert_objects([bucket_copy], tmp_path / "out", _fast_config(tmp_path / "cache"), progress=False)
    assert record.status == "failed" and "original-1.obj" in record.reason
