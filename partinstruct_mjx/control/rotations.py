"""Pure-JAX rotation helpers for batched kinematics; quaternions are MuJoCo's (w, x, y, z).

Every function broadcasts over leading axes. Euler angles follow the original's action convention: scipy's
lower-case 'xyz' (extrinsic, fixed axes), R = Rz(yaw) Ry(pitch) Rx(roll), as PyBullet's getQuaternionFromEuler.
"""

from __future__ import annotations

import jax.numpy as jnp

_GIMBAL_EPS = 1e-6
"""cos(pitch) below which Euler angles are in gimbal lock and yaw is set to 0 (as scipy does)."""


def quat_multiply(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Hamilton product a * b (apply b, then a)."""
    aw, ax, ay, az = jnp.moveaxis(a, -1, 0)
    bw, bx, by, bz = jnp.moveaxis(b, -1, 0)
    return jnp.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def quat_conjugate(q: jnp.ndarray) -> jnp.ndarray:
    """Inverse of a unit quaternion."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_rotate(q: jnp.ndarray, v: jnp.ndarray) -> jnp.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4)."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * jnp.cross(u, v)
    return v + w * t + jnp.cross(u, t)


def quat_to_matrix(q: jnp.ndarray) -> jnp.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4)."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def matrix_to_quat(m: jnp.ndarray) -> jnp.ndarray:
    """Unit quaternions (w >= 0) of rotation matrices (..., 3, 3), by Shepperd's method (branch-free)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    d21, s21 = m[..., 2, 1] - m[..., 1, 2], m[..., 2, 1] + m[..., 1, 2]
    d02, s02 = m[..., 0, 2] - m[..., 2, 0], m[..., 0, 2] + m[..., 2, 0]
    d10, s10 = m[..., 1, 0] - m[..., 0, 1], m[..., 1, 0] + m[..., 0, 1]
    trace = m00 + m11 + m22
    # Each candidate is 4 * (its largest component) times the quaternion; take the best-conditioned one.
    # Selecting with `where` (not a gather) keeps this element-wise under vmap.
    by_trace = jnp.stack([1 + trace, d21, d02, d10], axis=-1)
    by_x = jnp.stack([d21, 1 + m00 - m11 - m22, s10, s02], axis=-1)
    by_y = jnp.stack([d02, s10, 1 - m00 + m11 - m22, s21], axis=-1)
    by_z = jnp.stack([d10, s02, s21, 1 - m00 - m11 + m22], axis=-1)
    by_diag = jnp.where(((m00 >= m11) & (m00 >= m22))[..., None], by_x, jnp.where((m11 >= m22)[..., None], by_y, by_z))
    q = jnp.where((trace >= jnp.maximum(m00, jnp.maximum(m11, m22)))[..., None], by_trace, by_diag)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., :1] < 0, -q, q)


def axis_angle_to_quat(axis: jnp.ndarray, angle: jnp.ndarray) -> jnp.ndarray:
    """Quaternions rotating by `angle` (...) radians about unit `axis` (..., 3)."""
    half = 0.5 * jnp.asarray(angle)[..., None]
    return jnp.concatenate([jnp.cos(half), jnp.sin(half) * axis], axis=-1)


def quat_error(q_target: jnp.ndarray, q_current: jnp.ndarray) -> jnp.ndarray:
    """World-frame rotation vector (..., 3) turning q_current into q_target the short way: log(q_t * q_c^-1)."""
    dq = quat_multiply(q_target, quat_conjugate(q_current))
    dq = jnp.where(dq[..., :1] < 0, -dq, dq)
    w, v = dq[..., 0], dq[..., 1:]
    sin_half = jnp.linalg.norm(v, axis=-1)
    small = sin_half < 1e-6
    # angle / sin(angle / 2); its limit 2 / w as the angle goes to 0 keeps the gradient finite.
    scale = jnp.where(small, 2.0 / w, 2.0 * jnp.arctan2(sin_half, w) / jnp.where(small, 1.0, sin_half))
    return v * scale[..., None]


def euler_xyz_to_quat(euler: jnp.ndarray) -> jnp.ndarray:
    """Quaternions of extrinsic 'xyz' Euler angles (..., 3) = (roll, pitch, yaw): q = qz(yaw) qy(pitch) qx(roll)."""
    half = 0.5 * euler
    c, s = jnp.cos(half), jnp.sin(half)
    cr, cp, cy = c[..., 0], c[..., 1], c[..., 2]
    sr, sp, sy = s[..., 0], s[..., 1], s[..., 2]
    return jnp.stack([
        cy * cp * cr + sy * sp * sr,
        cy * cp * sr - sy * sp * cr,
        cy * sp * cr + sy * cp * sr,
        sy * cp * cr - cy * sp * sr,
    ], axis=-1)


def quat_to_euler_xyz(quat: jnp.ndarray) -> jnp.ndarray:
    """Extrinsic 'xyz' Euler angles (roll, pitch, yaw) in scipy's ranges: roll, yaw in [-pi, pi], pitch in
    [-pi/2, pi/2].

    In gimbal lock (|pitch| = pi/2) yaw is set to 0 and roll carries the whole rotation about x, as in scipy.
    """
    m = quat_to_matrix(quat / jnp.linalg.norm(quat, axis=-1, keepdims=True))
    cos_pitch = jnp.hypot(m[..., 0, 0], m[..., 1, 0])
    pitch = jnp.arctan2(-m[..., 2, 0], cos_pitch)
    locked = cos_pitch < _GIMBAL_EPS
    roll = jnp.where(locked, jnp.arctan2(-m[..., 2, 0] * m[..., 0, 1], m[..., 1, 1]),
                     jnp.arctan2(m[..., 2, 1], m[..., 2, 2]))
    yaw = jnp.where(locked, 0.0, jnp.arctan2(m[..., 1, 0], m[..., 0, 0]))
    return jnp.stack([roll, pitch, yaw], axis=-1)
