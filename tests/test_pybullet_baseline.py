"""The PyBullet baseline of the CPU benchmark: builds, IK follows, the object rests on the table, the workload grasps."""

import numpy as np
import pytest

pytest.importorskip("pybullet")

from partinstruct_mjx import paths  # noqa: E402
from partinstruct_mjx.bench.pybullet_baseline import (  # noqa: E402
    CLOUD_POINTS, HOME_TCP_POS, PyBulletScene, pybullet_rate)

MUG = paths.assets_root() / "objects" / "mug" / "mug_000" / "object.xml"


@pytest.fixture(scope="module")
def scene():
    with PyBulletScene(MUG, part="handle", settle_steps=30) as scene:
        yield scene


def test_builds_at_home_with_the_object_on_the_table(scene):
    pos, quat = scene.tcp_pose()
    np.testing.assert_allclose(pos, [0.5748, 0.5751, 0.3478], atol=1e-3)  # spec 1.3 home TCP
    np.testing.assert_allclose(np.abs(quat), np.abs([0.2656, 0.9591, -0.0876, -0.0446]), atol=1e-3)
    assert scene.object_cloud.shape == scene.part_cloud.shape == (CLOUD_POINTS, 3)
    predicates = scene.predicates()
    assert predicates["on"] and predicates["gripper_open"] and not predicates["grasping"]
    base, _ = scene.p.getBasePositionAndOrientation(scene.object, physicsClientId=scene.client)
    assert np.linalg.norm(np.asarray(base[:2]) - [0.0, -0.03]) < 0.03  # placed where our env places it


def test_tcp_follows_the_target(scene):
    target = HOME_TCP_POS + [0.0, -0.03, -0.04]
    scene.reset()
    for _ in range(60):  # 3 s; kp = 0.01 is a 0.42 s lag
        assert not scene.step_like_the_original(target)  # nothing grasped: the grasp skill stays unmet
    np.testing.assert_allclose(scene.tcp_pose()[0], target, atol=2e-3)
    assert scene.predicates()["on"] and scene.skill == 0


def test_workload_grasps_the_handle_and_returns_a_positive_rate(scene):
    assert pybullet_rate(scene, 30) > 0  # the approach, then the descent and 20 closed steps
    assert scene.predicates()["grasping"]
    assert scene.skill == 1  # the handle grasp met the grasp skill's check; the move's check runs now
