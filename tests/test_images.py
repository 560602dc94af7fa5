"""OpenGL camera observations: images, part masks with occlusion, depth point clouds, videos of trajectories."""

import argparse

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from partinstruct_mjx.errors import SceneError
from partinstruct_mjx.obs.cameras import project, world_to_optical
from partinstruct_mjx.obs.depth_cloud import PCD_SIZE, camera_observations, farthest_point_sample
from partinstruct_mjx.obs.images import ImageRenderer, backproject
from partinstruct_mjx.obs.render_cli import add_render_parser
from partinstruct_mjx.obs.video import load_trajectory, render_video, save_trajectory
from partinstruct_mjx.paths import assets_root
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
from partinstruct_mjx.sim.scene import SceneConfig, build_scene
from partinstruct_mjx.tasks import predicates
from partinstruct_mjx.tasks.part_geometry import spatial_masks

MUG = assets_root() / "objects" / "mug" / "mug_000" / "object.xml"


@pytest.fixture(scope="module")
def mug_scene():
    return build_scene(SceneConfig(object_xml=str(MUG)))


@pytest.fixture(scope="module")
def settled(mug_scene):
    """A C-backend SceneState row: robot at home, the mug settled at the spec's example position (0, -0.03)."""
    with MujocoBackend(mug_scene, 1) as backend:
        state = backend.reset(np.array([[0.0, -0.03]]))
    return jax.tree_util.tree_map(lambda x: x[0], state)


@pytest.fixture(scope="module")
def renderer(mug_scene):
    with ImageRenderer(mug_scene) as r:
        yield r


def _masks(row, renderer):
    return spatial_masks(predicates.object_points(row, renderer.geometry))


def _on_object(renderer, segmentation):
    return (segmentation >= 0) & (renderer.scene.geom_part[segmentation] >= 0)


def _with_object_yaw(scene, row, yaw):
    qpos = np.array(row.qpos)
    adr = scene.object_qpos_adr
    qpos[adr + 3: adr + 7] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
    return qpos


def test_observation_keys_shapes_and_dtypes(renderer, settled):
    part = renderer.part_names.index("handle")
    obs = camera_observations(renderer, settled, part, _masks(settled, renderer), wrist=True)
    expected = {
        "agentview_rgb": ((300, 300, 3), np.uint8), "agentview_pcd": ((PCD_SIZE, 3), np.float32),
        "agentview_pcd_world": ((PCD_SIZE, 3), np.float32), "agentview_part_pcd": ((PCD_SIZE, 4), np.float32),
        "agentview_part_mask": ((300, 300), np.uint8), "agentview_intrinsics": ((3, 3), np.float64),
        "agentview_extrinsics": ((4, 4), np.float64), "wrist_rgb": ((300, 300, 3), np.uint8),
        "wrist_part_pcd": ((PCD_SIZE, 3), np.float32), "wrist_part_pcd_world": ((PCD_SIZE, 3), np.float32),
        "wrist_part_mask": ((300, 300), np.uint8), "wrist_intrinsics": ((3, 3), np.float64),
        "wrist_extrinsics": ((4, 4), np.float64),
    }
    assert {k: (v.shape, v.dtype) for k, v in obs.items()} == expected
    assert set(np.unique(obs["agentview_part_mask"])) <= {0, 1}
    assert obs["agentview_part_mask"].sum() > 0
    np.testing.assert_allclose(obs["agentview_intrinsics"][0, 0], 150 / np.tan(np.radians(30)))  # spec 1.5
    np.testing.assert_allclose(obs["wrist_intrinsics"][0, 0], 200.0, rtol=1e-4)
    # The optical-frame and world clouds are the same points; the wrist cloud is the handle in its camera frame.
    extrinsics = obs["agentview_extrinsics"]
    world = np.c_[obs["agentview_pcd_world"], np.ones(PCD_SIZE)] @ extrinsics.T
    np.testing.assert_allclose(world[:, :3], obs["agentview_pcd"], atol=1e-4)
    handle, _ = predicates.part_cloud(settled, renderer.geometry, _masks(settled, renderer), part)
    assert cKDTree(np.asarray(handle)).query(obs["wrist_part_pcd_world"])[0].max() < 1e-3
    wrist = np.c_[obs["wrist_part_pcd_world"], np.ones(PCD_SIZE)] @ obs["wrist_extrinsics"].T
    np.testing.assert_allclose(wrist[:, :3], obs["wrist_part_pcd"], atol=1e-4)


def test_object_centre_projects_into_the_object_segmentation(renderer, settled):
    images = renderer.render(settled)
    u, v = np.asarray(project(world_to_optical(jnp.array([0.0, -0.03, 0.1]), images.position, images.rotation),
                              images.intrinsics))
    assert abs(u - 168) < 1.5 and abs(v - 214) < 1.5  # spec 1.5
    centre = np.asarray(predicates.object_points(settled, renderer.geometry)).mean(axis=0)
    u, v = np.asarray(project(world_to_optical(centre, images.position, images.rotation), images.intrinsics))
    assert _on_object(renderer, images.segmentation)[int(v), int(u)]
    assert images.segmentation.min() == -1 and images.depth.dtype == np.float32


def test_depth_backprojects_onto_the_object_surface(renderer, settled):
    images = renderer.render(settled)
    rows, cols = np.nonzero(_on_object(renderer, images.segmentation))
    assert len(rows) > 300
    points = backproject(images.depth[rows, cols], rows, cols, images.intrinsics)
    world = points @ images.rotation.T + images.position
    distance = cKDTree(np.asarray(predicates.object_points(settled, renderer.geometry))).query(world)[0]
    # parts.npz samples lie ~2.5 mm apart, so a pixel on the surface is within a few mm of one.
    assert np.median(distance) < 0.004 and distance.max() < 0.01


def test_handle_mask_is_occluded_behind_the_body(renderer, mug_scene, settled):
    data = np.load(MUG.parent / "parts.npz")
    handle = data["points"][list(data["part_names"]).index("handle")].mean(axis=0)
    facing = np.arctan2(handle[1], handle[0])
    part, masks = renderer.part_names.index("handle"), _masks(settled, renderer)
    counts = {}
    for name, direction in (("front", np.pi), ("back", 0.0)):  # the camera looks along +x: front faces it
        images = renderer.render(_with_object_yaw(mug_scene, settled, direction - facing))
        counts[name] = renderer.part_mask(images, part, masks).sum()
    assert counts["front"] > 20 and counts["back"] < counts["front"] / 3


def test_spatial_and_whole_object_masks(renderer, settled):
    images = renderer.render(settled)
    geo, masks = renderer.geometry, _masks(settled, renderer)
    on_object = _on_object(renderer, images.segmentation)
    whole = renderer.part_mask(images, geo.whole, masks)
    np.testing.assert_array_equal(whole.astype(bool), on_object)
    counts = {w: renderer.part_mask(images, renderer.part_names.index(w), masks).sum() for w in ("front", "back", "left", "right")}
    assert counts["front"] > counts["back"]  # 'front' is -x, towards the camera (spec 3.1)
    for word in ("left", "right"):
        mask = renderer.part_mask(images, renderer.part_names.index(word), masks).astype(bool)
        assert mask.any() and not (mask & ~on_object).any()
    assert not renderer.part_mask(images, None, masks).any()


def test_part_column_matches_the_mask(renderer, settled):
    geo, masks = renderer.geometry, _masks(settled, renderer)
    for part in (renderer.part_names.index("body"), renderer.part_names.index("front")):
        obs = camera_observations(renderer, settled, part, masks)
        cloud = obs["agentview_part_pcd"]
        pixels = np.floor(np.asarray(project(cloud[:, :3], obs["agentview_intrinsics"]))).astype(int)
        np.testing.assert_array_equal(cloud[:, 3], obs["agentview_part_mask"][pixels[:, 1], pixels[:, 0]])
        assert 0 < cloud[:, 3].sum() < PCD_SIZE
    obs = camera_observations(renderer, settled, None, masks)
    assert not obs["agentview_part_pcd"][:, 3].any() and not obs["agentview_part_mask"].any()


def test_wrist_camera_follows_the_hand(renderer, mug_scene, settled):
    moved = np.array(settled.qpos)
    moved[mug_scene.arm_qpos_adr[0]] += 0.3
    before, after = renderer.render(settled, "wrist"), renderer.render(moved, "wrist")
    assert np.linalg.norm(after.position - before.position) > 0.1
    assert np.abs(after.rgb.astype(int) - before.rgb.astype(int)).mean() > 5
    static = [renderer.render(q, "agentview") for q in (settled, moved)]
    np.testing.assert_array_equal(static[0].position, static[1].position)


def test_a_row_of_jax_arrays_renders_like_numpy(renderer, settled):
    """MJX rows hold jax arrays; only qpos is read, so both backends render alike."""
    as_jax = jax.tree_util.tree_map(jnp.asarray, settled)
    np.testing.assert_array_equal(renderer.render(as_jax).segmentation, renderer.render(settled).segmentation)


def test_farthest_point_sample_is_deterministic_and_spread():
    points = np.random.default_rng(0).normal(size=(3000, 3))
    chosen = farthest_point_sample(points, 64)
    assert chosen[0] == 0 and len(set(chosen.tolist())) == 64
    assert chosen[1] == np.argmax(np.linalg.norm(points - points[0], axis=1))
    np.testing.assert_array_equal(chosen, farthest_point_sample(points, 64))
    few = farthest_point_sample(points[:3], 5)
    assert sorted(few[:3].tolist()) == [0, 1, 2] and few[3:].tolist() == [0, 0]
    assert len(farthest_point_sample(np.zeros((0, 3)), 8)) == 0


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")
def test_render_command_writes_a_playable_mp4(mug_scene, tmp_path):
    qpos = []
    with MujocoBackend(mug_scene, 1) as backend:
        backend.reset()
        for k in range(6):
            ctrl = panda.HOME_CTRL.copy()
            ctrl[0] += 0.1 * k
            qpos.append(np.asarray(backend.step(ctrl[None]).qpos[0]))
    path = tmp_path / "traj.npz"
    save_trajectory(path, mug_scene, np.array(qpos), part=["handle"] * 3 + ["left"] * 3)
    trajectory = load_trajectory(path)
    assert trajectory.qpos.shape == (6, mug_scene.model.nq) and trajectory.object_xml == MUG.resolve()
    assert str(np.load(path)["object_xml"]) == "objects/mug/mug_000/object.xml"

    parser = argparse.ArgumentParser()
    add_render_parser(parser.add_subparsers())
    args = parser.parse_args(["render", str(path), "--out", str(tmp_path / "v.mp4"), "--wrist", "--fps", "10"])
    assert args.func(args) == 0
    frames = list(iio.imiter(tmp_path / "v.mp4"))
    assert len(frames) == 6 and frames[0].shape == (300, 600, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["traj.npz", "v.mp4"]  # no temporary files left


def test_bad_trajectory_files_raise_clear_errors(mug_scene, tmp_path):
    with pytest.raises(SceneError, match="not found"):
        load_trajectory(tmp_path / "missing.npz")
    text = tmp_path / "text.npz"
    text.write_text("not a zip")
    with pytest.raises(SceneError, match="text.npz: not a trajectory"):
        load_trajectory(text)
    no_qpos = tmp_path / "no_qpos.npz"
    np.savez(no_qpos, object_xml=np.array(str(MUG)))
    with pytest.raises(SceneError, match="no_qpos.npz: missing qpos"):
        load_trajectory(no_qpos)
    narrow = tmp_path / "narrow.npz"
    np.savez(narrow, qpos=np.zeros((3, 5)), object_xml=np.array(str(MUG)))
    with pytest.raises(SceneError, match=r"narrow.npz: qpos has 5 columns .* nq = "):
        render_video(narrow, tmp_path / "out.mp4")
    assert not (tmp_path / "out.mp4").exists()
    with pytest.raises(SceneError, match="qpos must have shape"):
        save_trajectory(tmp_path / "bad.npz", mug_scene, np.zeros((3, 5)))
