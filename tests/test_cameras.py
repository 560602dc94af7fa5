"""Camera geometry: poses equal MuJoCo's, intrinsics and projections equal the original's (spec 1.5)."""

import jax.numpy as jnp
import numpy as np
import pytest

from partinstruct_mjx.errors import SceneError
from partinstruct_mjx.obs.cameras import camera_pose, optical_to_world, project, scene_camera, world_to_optical
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend


@pytest.fixture(scope="module")
def settled(scene):
    with MujocoBackend(scene, 1) as backend:
        state = backend.reset()
        data = backend.datas[0]
        import mujoco

        mujoco.mj_forward(scene.model, data)
        return state, data.cam_xpos.copy(), data.cam_xmat.copy()


@pytest.mark.parametrize("name, focal", [("agentview", 259.80762), ("wrist", 200.0)])
def test_pose_and_intrinsics_match_mujoco_and_the_original(scene, settled, name, focal):
    state, cam_xpos, cam_xmat = settled
    camera = scene_camera(scene, name)
    position, rotation = camera_pose(camera, jnp.asarray(state.body_pos[0]), jnp.asarray(state.body_quat[0]))
    index = scene.model.camera(name).id
    np.testing.assert_allclose(position, cam_xpos[index], atol=1e-5)
    np.testing.assert_allclose(np.asarray(rotation) @ np.diag([1, -1, -1]), cam_xmat[index].reshape(3, 3), atol=1e-5)
    np.testing.assert_allclose(camera.intrinsics[0, 0], focal, rtol=1e-4)
    np.testing.assert_allclose(camera.intrinsics[:2, 2], [150, 150])


def test_projection_matches_the_originals_pixels(scene, settled):
    """Spec 1.5: an object at (0, -0.03, 0.1) projects to about (168, 214), the robot base to (157, 170)."""
    state = settled[0]
    camera = scene_camera(scene, "agentview")
    position, rotation = camera_pose(camera, jnp.asarray(state.body_pos[0]), jnp.asarray(state.body_quat[0]))
    points = jnp.array([[0.0, -0.03, 0.1], [0.6, 0.0, 0.05]])
    optical = world_to_optical(points, position, rotation)
    np.testing.assert_allclose(project(optical, camera.intrinsics), [[168, 214], [157, 170]], atol=0.6)
    np.testing.assert_allclose(optical_to_world(optical, position, rotation), points, atol=1e-6)
    assert (optical[:, 2] > 0).all()  # in front of the camera


def test_unknown_camera_is_named(scene):
    with pytest.raises(SceneError, match="unknown camera 'top'"):
        scene_camera(scene, "top")
