"""Batched damped-least-squares IK for the Panda TCP in JAX, with joint limits (spec 1.6: TCP pose -> arm joints).

The kinematic chain is read once from the compiled MjModel (`ArmKinematics.from_scene`), so the solver follows
the MJCF. A solve runs until the weighted pose error is below `IKConfig.tolerance` or `IKConfig.iterations` have run
(a batch iterates until all of its solves have stopped; iteration counts, never wall-clock time): each builds the
analytic geometric Jacobian from the world joint axes (9x faster than jax.jacfwd of the forward kinematics, measured
on a CPU), takes a Levenberg-Marquardt-damped least-squares step towards the target pose, limits it to `max_step` and
clamps it to the joint range. Joints that sit on a limit and are pushed outwards are dropped from the step, so the
other joints use the arm's redundancy instead of stalling against the limit (joint 1 works near its +-2.8973 limit
when the arm reaches back over the table)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from partinstruct_mjx.control import rotations as rot
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import Scene


@struct.dataclass
class ArmKinematics:
    """The serial chain from the robot base to the TCP site, as arrays (a pytree, so it can be a jit argument).

    Body i carries arm joint i; its offset is relative to body i-1 (the base for i = 0), with any joint-less bodies
    in between folded in. The TCP offset is relative to the last jointed body (panda_link7: hand and site composed).
    """

    base_pos: jnp.ndarray
    """(3,) world position of the fixed body the chain hangs from (panda_link0)."""
    base_quat: jnp.ndarray
    """(4,) its world orientation."""
    body_pos: jnp.ndarray
    """(7, 3) offset of each jointed body from the previous one."""
    body_quat: jnp.ndarray
    """(7, 4) orientation of each jointed body relative to the previous one."""
    joint_pos: jnp.ndarray
    """(7, 3) joint anchor in its body's frame."""
    joint_axis: jnp.ndarray
    """(7, 3) unit hinge axis in its body's frame."""
    joint_ref: jnp.ndarray
    """(7,) joint angle at which the body has its offset pose (MuJoCo's qpos0)."""
    lower: jnp.ndarray
    """(7,) lower joint limits, rad."""
    upper: jnp.ndarray
    """(7,) upper joint limits, rad."""
    tcp_pos: jnp.ndarray
    """(3,) TCP site position in the last jointed body's frame."""
    tcp_quat: jnp.ndarray
    """(4,) TCP site orientation in the last jointed body's frame."""

    @classmethod
    def from_scene(cls, scene: Scene) -> ArmKinematics:
        """The Panda chain of a built scene."""
        return cls.from_model(scene.model)

    @classmethod
    def from_model(cls, model: mujoco.MjModel, joints: tuple[str, ...] = panda.ARM_JOINTS,
                   site: str = panda.TCP_SITE) -> ArmKinematics:
        """Extract the chain of hinge `joints` (base to tip) ending at `site`; raises ValueError if it is not one."""
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        joint_ids = [_named_id(model, mujoco.mjtObj.mjOBJ_JOINT, name) for name in joints]
        site_id = _named_id(model, mujoco.mjtObj.mjOBJ_SITE, site)
        chain = _body_path(model, model.site_bodyid[site_id])
        joint_bodies = [int(model.jnt_bodyid[j]) for j in joint_ids]
        for name, j, body in zip(joints, joint_ids, joint_bodies):
            if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
                raise ValueError(f"joint {name!r} is a {mujoco.mjtJoint(model.jnt_type[j]).name}, not a hinge")
            if body not in chain:
                raise ValueError(f"joint {name!r} is not on the chain from the world to site {site!r}")
        positions = [chain.index(body) for body in joint_bodies]
        if positions != sorted(set(positions)):
            raise ValueError(f"joints {joints} must sit on distinct bodies, ordered from the base to site {site!r}")
        for body in chain:
            others = set(range(model.body_jntadr[body], model.body_jntadr[body] + model.body_jntnum[body]))
            if others - set(joint_ids):
                raise ValueError(f"body {model.body(body).name!r} on the arm chain has a joint not in {joints}")

        base = chain[positions[0] - 1]
        body_pos, body_quat = [], []
        for start, stop in zip([positions[0] - 1, *positions[:-1]], positions):
            pos, quat = _compose_offsets(model, chain[start + 1:stop + 1])
            body_pos.append(pos)
            body_quat.append(quat)
        hand_pos, hand_quat = _compose_offsets(model, chain[positions[-1] + 1:])
        tcp_pos = hand_pos + _rotate(hand_quat, model.site_pos[site_id])
        tcp_quat = _multiply(hand_quat, model.site_quat[site_id])
        limited = model.jnt_limited[joint_ids].astype(bool)
        lower = np.where(limited, model.jnt_range[joint_ids, 0], -np.inf)
        upper = np.where(limited, model.jnt_range[joint_ids, 1], np.inf)
        as_jnp = jnp.asarray  # float32 unless jax_enable_x64
        return cls(
            base_pos=as_jnp(data.xpos[base]), base_quat=as_jnp(data.xquat[base]),
            body_pos=as_jnp(np.stack(body_pos)), body_quat=as_jnp(np.stack(body_quat)),
            joint_pos=as_jnp(model.jnt_pos[joint_ids]), joint_axis=as_jnp(model.jnt_axis[joint_ids]),
            joint_ref=as_jnp(model.qpos0[model.jnt_qposadr[joint_ids]]),
            lower=as_jnp(lower), upper=as_jnp(upper),
            tcp_pos=as_jnp(tcp_pos), tcp_quat=as_jnp(tcp_quat),
        )


@dataclass(frozen=True)
class IKConfig:
    """Iteration budget and step rules of `solve_ik` (iteration counts, never wall-clock time).

    The defaults were tuned on workspace targets (`partinstruct_mjx/bench/ik.py`): closed-loop servo targets converge
    in 3 iterations, targets across the workspace reached from the home pose in 10 (99.5 %) to 15 (100 %).

    Attributes:
      iterations: most damped least-squares iterations per solve.
      tolerance: a solve stops once the weighted pose error (metres, plus orientation_weight x radians) it just
        stepped from is below this (0: always run `iterations`).
      damping: lambda of (J J^T + lambda^2 I): keeps steps bounded next to singular configurations.
      error_damping: adds error_damping * |weighted error|^2 to lambda^2 (Levenberg-Marquardt style), so far
        targets take short, safe steps and near ones converge quadratically.
      max_step: largest joint change per iteration, rad; the whole step is scaled down to respect it.
      orientation_weight: how many metres of position error one radian of orientation error counts as.
    """

    iterations: int = 20
    tolerance: float = 1e-5
    damping: float = 3e-3
    error_damping: float = 0.1
    max_step: float = 0.8
    orientation_weight: float = 1.0

    def __post_init__(self):
        if self.iterations < 1:
            raise ValueError(f"IKConfig.iterations must be >= 1, got {self.iterations}")
        for name in ("damping", "max_step", "orientation_weight"):
            if not getattr(self, name) > 0:
                raise ValueError(f"IKConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("error_damping", "tolerance"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"IKConfig.{name} must be >= 0, got {getattr(self, name)}")


def _frames(kin: ArmKinematics, q: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """World joint anchors (7, 3), world joint axes (7, 3), TCP position (3,) and rotation matrix (3, 3)."""
    rot_mat = rot.quat_to_matrix(kin.base_quat)
    pos = kin.base_pos
    body_mat = rot.quat_to_matrix(kin.body_quat)
    anchors, axes = [], []
    for i in range(q.shape[-1]):
        pos = pos + _matmul(rot_mat, kin.body_pos[i])
        rot_mat = _matmul(rot_mat, body_mat[i])
        anchor = pos + _matmul(rot_mat, kin.joint_pos[i])
        axis = _matmul(rot_mat, kin.joint_axis[i])
        rot_mat = _matmul(rot_mat, _axis_angle_matrix(kin.joint_axis[i], q[i] - kin.joint_ref[i]))
        pos = anchor - _matmul(rot_mat, kin.joint_pos[i])
        anchors.append(anchor)
        axes.append(axis)
    tcp_pos = pos + _matmul(rot_mat, kin.tcp_pos)
    tcp_mat = _matmul(rot_mat, rot.quat_to_matrix(kin.tcp_quat))
    return jnp.stack(anchors), jnp.stack(axes), tcp_pos, tcp_mat


def _matmul(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """a @ b in full float32: on a GPU XLA runs float32 dots in TF32 by default, 0.3 mm of TCP error on an H100."""
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def _axis_angle_matrix(axis: jnp.ndarray, angle: jnp.ndarray) -> jnp.ndarray:
    """Rodrigues' rotation matrix about a unit axis."""
    k = jnp.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return jnp.eye(3) + jnp.sin(angle) * k + (1.0 - jnp.cos(angle)) * _matmul(k, k)


def forward_kinematics(kin: ArmKinematics, q: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """TCP position (3,) and orientation (4,) (w, x, y, z) in the world for arm joint angles q (7,)."""
    _, _, tcp_pos, tcp_mat = _frames(kin, q)
    return tcp_pos, rot.matrix_to_quat(tcp_mat)


batched_forward_kinematics = jax.vmap(forward_kinematics, in_axes=(None, 0))
"""forward_kinematics over a batch: q (B, 7) -> (B, 3), (B, 4)."""


def jacobian(kin: ArmKinematics, q: jnp.ndarray) -> jnp.ndarray:
    """Geometric Jacobian (6, 7) of the TCP: rows = world linear velocity, then world angular velocity."""
    anchors, axes, tcp_pos, _ = _frames(kin, q)
    return _jacobian(anchors, axes, tcp_pos)


def _jacobian(anchors: jnp.ndarray, axes: jnp.ndarray, tcp_pos: jnp.ndarray,
              angular_weight: float = 1.0) -> jnp.ndarray:
    return jnp.concatenate([jnp.cross(axes, tcp_pos - anchors).T, angular_weight * axes.T], axis=0)


def _ik_step(kin: ArmKinematics, config: IKConfig, target_pos: jnp.ndarray, target_quat: jnp.ndarray,
             q: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """One damped least-squares step, limited to `max_step` and clamped to the joint limits, and the norm of the
    weighted pose error at `q` it stepped from.

    A second pass re-solves without the joints that sit on a limit and are pushed outwards, so the other joints
    make up for them (mink gets the same effect from its QP's limit constraints).
    """
    anchors, axes, tcp_pos, tcp_mat = _frames(kin, q)
    weight = config.orientation_weight
    jac = _jacobian(anchors, axes, tcp_pos, weight)
    rot_error = rot.quat_error(target_quat, rot.matrix_to_quat(tcp_mat))
    error = jnp.concatenate([target_pos - tcp_pos, weight * rot_error])
    damping = (config.damping ** 2 + config.error_damping * jnp.sum(error ** 2)) * jnp.eye(6, dtype=q.dtype)
    free = jnp.ones_like(q)
    for _ in range(2):
        masked = jac * free
        dq = _matmul(masked.T, _spd_solve(_matmul(masked, masked.T) + damping, error))
        blocked = ((q <= kin.lower) & (dq < 0)) | ((q >= kin.upper) & (dq > 0))
        free = jnp.where(blocked, 0.0, free)
    dq = dq * jnp.minimum(1.0, config.max_step / (jnp.max(jnp.abs(dq)) + 1e-12))
    return jnp.clip(q + dq, kin.lower, kin.upper), jnp.linalg.norm(error)


def _spd_solve(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Solve a x = b for a small symmetric positive-definite a by an unrolled Cholesky factorisation.

    Element-wise code vectorises across a vmapped batch (no per-item LAPACK calls).
    """
    n = b.shape[0]
    low = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            s = a[i, j] - sum(low[i][k] * low[j][k] for k in range(j))
            low[i][j] = jnp.sqrt(s) if i == j else s / low[j][j]
    y = []
    for i in range(n):
        y.append((b[i] - sum(low[i][k] * y[k] for k in range(i))) / low[i][i])
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) / low[i][i]
    return jnp.stack(x)


def _solve_one(kin: ArmKinematics, config: IKConfig, q_init: jnp.ndarray, target_pos: jnp.ndarray,
               target_quat: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    target_quat = target_quat / jnp.linalg.norm(target_quat)
    q = jnp.clip(q_init, kin.lower, kin.upper)

    def unfinished(carry):
        iteration, _, error = carry
        return (iteration < config.iterations) & (error >= config.tolerance)

    def step(carry):
        iteration, q, _ = carry
        return (iteration + 1, *_ik_step(kin, config, target_pos, target_quat, q))

    _, q, _ = jax.lax.while_loop(unfinished, step, (0, q, jnp.asarray(jnp.inf, q.dtype)))
    tcp_pos, tcp_quat = forward_kinematics(kin, q)
    return q, jnp.linalg.norm(target_pos - tcp_pos), jnp.linalg.norm(rot.quat_error(target_quat, tcp_quat))


@partial(jax.jit, static_argnames="config")
def _solve_batch(kin: ArmKinematics, q_init: jnp.ndarray, target_pos: jnp.ndarray, target_quat: jnp.ndarray,
                 config: IKConfig) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    return jax.vmap(_solve_one, in_axes=(None, None, 0, 0, 0))(kin, config, q_init, target_pos, target_quat)


MIN_BATCH = 4
"""Smaller batches are solved padded to this many rows (their first row repeated): XLA on a CPU vectorises the
batched solve differently for 1 or 2 rows, which then end 1 ulp away from the same rows solved in a larger batch, and
an oracle episode run in a batch of 1 or 2 drifted from the same episode in a batch of 4 after 65 steps. Larger
batch shapes may round differently from each other too, depending on the CPU (on an AVX2-only EPYC a batch of 4 or 6
rounds 1 ulp away from the same rows in a batch of 16, one of 5, 7, 8 or 12 does not)."""


def solve_ik(kin: ArmKinematics, q_init: jnp.ndarray, target_pos: jnp.ndarray, target_quat: jnp.ndarray,
             config: IKConfig = IKConfig()) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Arm joint angles (B, 7) reaching TCP targets, seeded from q_init (B, 7); compiled once per batch size and config.

    target_pos (B, 3) in metres, target_quat (B, 4) (w, x, y, z). Returns the joint angles (inside the limits),
    the remaining position error (B,) in metres and the rotation error (B,) in radians.
    """
    batch = _check_shape("q_init", q_init, (None, kin.lower.shape[0]))
    _check_shape("target_pos", target_pos, (batch, 3))
    _check_shape("target_quat", target_quat, (batch, 4))
    pad = max(0, MIN_BATCH - batch)
    if pad:
        q_init, target_pos, target_quat = (jnp.concatenate([x, jnp.repeat(x[:1], pad, axis=0)])
                                           for x in (q_init, target_pos, target_quat))
    q, position_error, rotation_error = _solve_batch(kin, q_init, target_pos, target_quat, config)
    return q[:batch], position_error[:batch], rotation_error[:batch]


def actions_to_targets(actions: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Split (B, 6) pose actions (x, y, z, roll, pitch, yaw; extrinsic 'xyz' Euler) into (B, 3) and (B, 4) targets."""
    _check_shape("actions", actions, (None, 6))
    return actions[:, :3], rot.euler_xyz_to_quat(actions[:, 3:])


def _check_shape(name: str, array, expected: tuple[int | None, ...]) -> int:
    """Raise ValueError unless `array` has shape `expected` (None = any size); return the leading size."""
    shape = jnp.shape(array)
    if len(shape) != len(expected) or any(e is not None and s != e for s, e in zip(shape, expected)):
        wanted = "(" + ", ".join("B" if e is None else str(e) for e in expected) + ")"
        raise ValueError(f"{name} must have shape {wanted}, got {shape}")
    return shape[0]


def _named_id(model: mujoco.MjModel, kind: mujoco.mjtObj, name: str) -> int:
    index = mujoco.mj_name2id(model, kind, name)
    if index < 0:
        raise ValueError(f"the model has no {kind.name[6:].lower()} named {name!r}")
    return index


def _body_path(model: mujoco.MjModel, body: int) -> list[int]:
    """Body ids from the world (0) down to `body`."""
    path = [body]
    while path[-1] != 0:
        path.append(int(model.body_parentid[path[-1]]))
    return path[::-1]


def _compose_offsets(model: mujoco.MjModel, bodies: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the last of `bodies` relative to the parent of the first, composing their fixed offsets."""
    pos, quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
    for body in bodies:
        pos = pos + _rotate(quat, model.body_pos[body])
        quat = _multiply(quat, model.body_quat[body])
    return pos, quat


def _rotate(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    out = np.zeros(3)
    mujoco.mju_rotVecQuat(out, np.asarray(vec, float), np.asarray(quat, float))
    return out


def _multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.zeros(4)
    mujoco.mju_mulQuat(out, np.asarray(a, float), np.asarray(b, float))
    return out
