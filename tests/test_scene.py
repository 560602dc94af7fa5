"""Scene assembly: object attachment, part labels, collision bits, cameras, and clear errors for bad objects."""

import mujoco
import numpy as np
import pytest

from partinstruct_mjx.assets.naming import geom_name, parse_geom_name
from partinstruct_mjx.errors import AssetError
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import OBJECT_BITS, TABLE_HEIGHT, SceneConfig, build_scene


def test_scene_has_the_object_with_its_parts(scene):
    assert scene.part_names == ("body", "lid")
    model = scene.model
    assert model.joint("object/root").type == mujoco.mjtJoint.mjJNT_FREE
    for g in scene.object_geoms:
        assert (model.geom_contype[g], model.geom_conaffinity[g]) == OBJECT_BITS
    assert len(scene.object_geoms) == 2
    np.testing.assert_allclose(model.body_mass[scene.object_body], 0.1)


def test_robot_base_pose_and_table(scene):
    data = mujoco.MjData(scene.model)
    mujoco.mj_kinematics(scene.model, data)
    np.testing.assert_allclose(data.xpos[scene.model.body("panda_link0").id], panda.BASE_POS)
    table = scene.model.geom("table")
    assert table.type == mujoco.mjtGeom.mjGEOM_PLANE
    assert table.pos[2] == pytest.approx(TABLE_HEIGHT)


def test_agentview_camera_matches_the_original(scene):
    data = mujoco.MjData(scene.model)
    mujoco.mj_forward(scene.model, data)
    cam = scene.model.camera("agentview").id
    np.testing.assert_allclose(data.cam_xpos[cam], [-1.00175, 0.05, 0.77362])
    rot = data.cam_xmat[cam].reshape(3, 3)
    np.testing.assert_allclose(-rot[:, 2], [0.93969, 0.0, -0.34202], atol=1e-4)  # viewing direction, spec 1.5


def test_parts_never_collide_with_each_other_or_the_arm(scene):
    model = scene.model

    def collides(a, b):
        return bool(model.geom_contype[a] & model.geom_conaffinity[b] or model.geom_contype[b] & model.geom_conaffinity[a])

    body, lid = scene.object_geoms
    assert not collides(body, lid)
    arm_link = model.geom(next(g for g in range(model.ngeom) if model.geom_bodyid[g] == model.body("panda_link4").id
                               and model.geom_contype[g])).id
    pad = model.geom("left_pad").id
    table = scene.table_geom
    assert collides(body, table) and collides(body, pad) and collides(arm_link, table)
    assert not collides(body, arm_link) and not collides(pad, arm_link)


def test_geom_names_round_trip():
    assert geom_name("containing things", "col", 3) == "containing_things/col3"
    assert parse_geom_name("object/containing_things/col3") == ("containing things", "col")
    assert parse_geom_name("object/lid/vis0") == ("lid", "vis")
    assert parse_geom_name("left_pad") is None


def _write(tmp_path, body: str):
    path = tmp_path / "object.xml"
    path.write_text(f"<mujoco><worldbody>{body}</worldbody></mujoco>")
    return str(path)


def test_missing_object_file_is_named(tmp_path):
    missing = tmp_path / "nope" / "object.xml"
    with pytest.raises(AssetError, match="nope/object.xml"):
        build_scene(SceneConfig(object_xml=str(missing)))


def test_malformed_object_file_is_named(tmp_path):
    path = tmp_path / "object.xml"
    path.write_text("<mujoco><worldbody><body name='base'><geom size='0.1' type='box'</worldbody>")
    with pytest.raises(AssetError, match="object.xml"):
        build_scene(SceneConfig(object_xml=str(path)))


def test_unlabelled_object_geom_is_rejected(tmp_path):
    path = _write(tmp_path, "<body name='base'><geom name='blob' type='box' size='.02 .02 .02'/></body>")
    with pytest.raises(AssetError, match="'object/blob'"):
        build_scene(SceneConfig(object_xml=path))


def test_object_without_collision_geoms_is_rejected(tmp_path):
    path = _write(tmp_path, "<body name='base'><geom name='body/vis0' type='box' size='.02 .02 .02' "
                            "contype='0' conaffinity='0'/></body>")
    with pytest.raises(AssetError, match="no collision geoms"):
        build_scene(SceneConfig(object_xml=path))


def test_object_with_two_root_bodies_is_rejected(tmp_path):
    path = _write(tmp_path, "<body name='a'><geom name='a/col0' size='.02'/></body>"
                            "<body name='b'><geom name='b/col0' size='.02'/></body>")
    with pytest.raises(AssetError, match="exactly one root body"):
        build_scene(SceneConfig(object_xml=path))


def test_a_closed_hand_squeezes_a_thin_part_with_over_20_newtons_per_finger(scene):
    # GRASPING needs > 20 N on one finger; a 2.6 mm eyeglasses temple leaves the fingers 1.3 mm open each, where the
    # hand, commanded closed, must still press that hard (aiming 12 mm past closed it gave 19.9 N). Fully open stays
    # fully open.
    model = scene.model
    data = mujoco.MjData(model)
    gripper = model.actuator("gripper").id
    cases = ((0.0013, panda.FINGER_CLOSED), (0.0, panda.FINGER_CLOSED), (panda.FINGER_OPEN, panda.FINGER_OPEN))
    for opening, ctrl in cases:
        data.qpos[scene.finger_qpos_adr] = opening
        data.qvel[:] = 0.0
        data.ctrl[gripper] = ctrl
        data.act[model.actuator_actadr[gripper]] = ctrl
        mujoco.mj_forward(model, data)
        per_finger = -0.5 * data.actuator_force[gripper]
        if ctrl == panda.FINGER_CLOSED:
            assert per_finger > 20.0
        else:
            assert abs(per_finger) < 1.0
