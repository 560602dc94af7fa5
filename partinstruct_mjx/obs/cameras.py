"""Camera geometry shared by the OpenGL image path and the JAX point-cloud renderer (spec 1.5).

Poses come from a SceneState row (body poses), so they are right for any backend and for the moving wrist camera.
The optical frame is the original's point-cloud frame: x right, y down, z forward (MuJoCo cameras look along -z
with y up, so the optical axes are (x, -y, -z) of the MuJoCo camera frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.control.rotations import quat_multiply, quat_to_matrix
from partinstruct_mjx.errors import SceneError
from partinstruct_mjx.sim.scene import Scene
from partinstruct_mjx.vectors import dot3

AGENTVIEW = "agentview"
WRIST = "wrist"
IMAGE_SIZE = 300
"""Both cameras render 300 x 300 (spec 1.5)."""
PCD_SIZE = 1024
"""Points per observation cloud (spec 2.1)."""

_MUJOCO_TO_OPTICAL = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class Camera:
    """A camera of the scene: the body it rides on, its pose on that body, and its pinhole intrinsics."""

    name: str
    body: int
    local_pos: np.ndarray
    local_quat: np.ndarray
    width: int
    height: int
    fovy: float
    """Vertical field of view, degrees."""

    @property
    def intrinsics(self) -> np.ndarray:
        """3x3 K with fx = fy = (height / 2) / tan(fovy / 2), principal point at the image centre (the original's)."""
        f = (self.height / 2) / np.tan(np.radians(self.fovy) / 2)
        return np.array([[f, 0.0, self.width / 2], [0.0, f, self.height / 2], [0.0, 0.0, 1.0]])


def scene_camera(scene: Scene, name: str, width: int = IMAGE_SIZE, height: int = IMAGE_SIZE) -> Camera:
    """The named camera of a scene ('agentview' or 'wrist'); SceneError naming an unknown camera."""
    model = scene.model
    try:
        cam = model.camera(name)
    except KeyError:
        names = [model.camera(i).name for i in range(model.ncam)]
        raise SceneError(f"unknown camera '{name}'; the scene has {', '.join(names)}") from None
    return Camera(name, int(cam.bodyid[0]), np.array(cam.pos), np.array(cam.quat), width, height, float(cam.fovy[0]))


def camera_pose(camera: Camera, body_pos: jnp.ndarray, body_quat: jnp.ndarray):
    """World position (3,) and optical-frame rotation (3, 3) (columns: x right, y down, z forward) of one scene."""
    position = body_pos[camera.body] + quat_to_matrix(body_quat[camera.body]) @ jnp.asarray(camera.local_pos)
    rotation = quat_to_matrix(quat_multiply(body_quat[camera.body], jnp.asarray(camera.local_quat)))
    return position, rotation @ jnp.asarray(_MUJOCO_TO_OPTICAL)


def world_to_optical(points: jnp.ndarray, position: jnp.ndarray, rotation: jnp.ndarray) -> jnp.ndarray:
    """World points (..., 3) -> optical-frame points (..., 3)."""
    d = points - position
    return jnp.stack([dot3(d, rotation[:, j]) for j in range(3)], axis=-1)  # not a K=3 matmul (vectors.py)


def optical_to_world(points: jnp.ndarray, position: jnp.ndarray, rotation: jnp.ndarray) -> jnp.ndarray:
    return points @ rotation.T + position


def project(points_optical: jnp.ndarray, intrinsics: np.ndarray) -> jnp.ndarray:
    """Optical-frame points (..., 3) -> pixel coordinates (..., 2) as (u right, v down), floats."""
    k = jnp.asarray(intrinsics)
    z = jnp.maximum(points_optical[..., 2:3], 1e-9)
    return points_optical[..., :2] / z * jnp.array([k[0, 0], k[1, 1]]) + jnp.array([k[0, 2], k[1, 2]])
