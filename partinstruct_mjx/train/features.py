"""What the network sees and predicts, converted from and to the benchmark's layouts.

Actions are stored and executed as [x, y, z, roll, pitch, yaw, finger] (spec 1.6), but the top-down grasps of the
demos put roll at +-pi, where Euler angles wrap: a regression or a denoiser averaging +pi and -pi returns 0, a
gripper turned upside down. The network therefore works with a continuous rotation, the first two columns of the
rotation matrix (the "6-D" representation Diffusion Policy uses for absolute actions), and the policy converts back.
The TCP quaternion of the proprioception gets the same treatment (q and -q are the same rotation).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from partinstruct_mjx.control.rotations import euler_xyz_to_quat, matrix_to_quat, quat_to_euler_xyz, quat_to_matrix

ACTION_DIM = 10
"""xyz (3), rotation-matrix columns 1-2 (6), finger opening (1)."""
PROPRIO_DIM = 17
"""TCP xyz (3), TCP rotation-matrix columns 1-2 (6), arm joints (7), left finger joint (1)."""
PROPRIO_KEYS = ("tcp_pose", "joint_states", "gripper_state")


def rotation_6d(matrix: jnp.ndarray) -> jnp.ndarray:
    """(..., 6): the first two columns of rotation matrices (..., 3, 3)."""
    return jnp.concatenate([matrix[..., :, 0], matrix[..., :, 1]], axis=-1)


def rotation_from_6d(six: jnp.ndarray) -> jnp.ndarray:
    """Rotation matrices (..., 3, 3) nearest to two (possibly noisy) columns (..., 6), by Gram-Schmidt."""
    a, b = six[..., :3], six[..., 3:]
    x = a / jnp.linalg.norm(a, axis=-1, keepdims=True)
    y = b - jnp.sum(x * b, axis=-1, keepdims=True) * x
    y = y / jnp.linalg.norm(y, axis=-1, keepdims=True)
    return jnp.stack([x, y, jnp.cross(x, y)], axis=-1)


@jax.jit
def actions_to_model(actions) -> jnp.ndarray:
    """(..., 10) network actions from (..., 7) Euler actions."""
    actions = jnp.asarray(actions, jnp.float32)
    matrix = quat_to_matrix(euler_xyz_to_quat(actions[..., 3:6]))
    return jnp.concatenate([actions[..., :3], rotation_6d(matrix), actions[..., 6:]], axis=-1)


@jax.jit
def actions_from_model(actions) -> jnp.ndarray:
    """(..., 7) Euler actions from (..., 10) network actions."""
    actions = jnp.asarray(actions, jnp.float32)
    euler = quat_to_euler_xyz(matrix_to_quat(rotation_from_6d(actions[..., 3:9])))
    return jnp.concatenate([actions[..., :3], euler, actions[..., 9:]], axis=-1)


@jax.jit
def proprio_features(tcp_pose, joint_states, gripper_state) -> jnp.ndarray:
    """(..., 17) from tcp_pose (..., 7) [qx, qy, qz, qw, x, y, z], joint_states (..., 7), gripper_state (..., 1)."""
    tcp_pose = jnp.asarray(tcp_pose, jnp.float32)
    quat = jnp.concatenate([tcp_pose[..., 3:4], tcp_pose[..., :3]], axis=-1)
    return jnp.concatenate([tcp_pose[..., 4:], rotation_6d(quat_to_matrix(quat)),
                            jnp.asarray(joint_states, jnp.float32), jnp.asarray(gripper_state, jnp.float32)], axis=-1)
