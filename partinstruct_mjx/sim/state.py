"""The batched `SceneState` pytree that both physics backends produce and everything above physics reads."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

MAX_FINGER_CONTACTS = 8
"""Contacts kept per finger (the strongest ones when there are more)."""
BODY_ROWS = 8
"""Body rows are padded to a multiple of this (scenes with a few more or fewer object links share compiled code)."""


def body_rows(nbody: int) -> int:
    """Rows of `SceneState.body_pos` for a model with `nbody` bodies."""
    return -(-nbody // BODY_ROWS) * BODY_ROWS


@struct.dataclass
class SceneState:
    """Physics state of a batch of B scenes. Quaternions are MuJoCo's (w, x, y, z); positions in metres, world frame.

    As in MuJoCo (and MJX), poses and contacts are those of the last physics substep's forward pass, i.e. one
    physics step (5 ms) behind `qpos`/`qvel`.

    Attributes:
      time: (B,) simulated seconds.
      qpos, qvel: (B, nq), (B, nv) full generalised coordinates (robot, then object).
      arm_qpos: (B, 7) arm joint angles.
      finger_qpos: (B, 2) finger slide positions (0 closed ... 0.04 open, each).
      tcp_pos, tcp_quat: (B, 3), (B, 4) tool centre point pose (spec 1.3).
      object_pos, object_quat: (B, 3), (B, 4) pose of the object's root body.
      body_pos, body_quat: (B, R, 3), (B, R, 4) every body's pose (object links move part points); R =
        `body_rows(nbody)`, the rows past nbody hold the origin and the identity.
      contact_pos: (B, 2, K, 3) contact points of the left (0) and right (1) finger.
      contact_force: (B, 2, K) contact normal forces in newtons; 0 in empty slots.
      contact_geom: (B, 2, K) the geom each finger touches; -1 in empty slots.
    """

    time: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    arm_qpos: np.ndarray
    finger_qpos: np.ndarray
    tcp_pos: np.ndarray
    tcp_quat: np.ndarray
    object_pos: np.ndarray
    object_quat: np.ndarray
    body_pos: np.ndarray
    body_quat: np.ndarray
    contact_pos: np.ndarray
    contact_force: np.ndarray
    contact_geom: np.ndarray

    @property
    def batch_size(self) -> int:
        return self.time.shape[0]

    def for_jit(self) -> SceneState | HostBlock:
        """This state as jitted functions take it (they call `unpacked` on it): without qpos and qvel, whose widths
        depend on the object's joints, so that functions compiled for one object serve every object with the same
        padded shapes. A host (NumPy) state travels as one `HostBlock`."""
        if isinstance(self.time, np.ndarray):
            return HostBlock.pack(self)
        return self.replace(qpos=None, qvel=None)

    @property
    def gripper_width(self):
        """(B,) distance between the finger pads: the sum of both finger positions."""
        return self.finger_qpos.sum(axis=-1)


_BLOCK_FIELDS = ("time", "arm_qpos", "finger_qpos", "tcp_pos", "tcp_quat", "object_pos", "object_quat", "body_pos",
                 "body_quat", "contact_pos", "contact_force")


@struct.dataclass
class HostBlock:
    """A host SceneState's float fields in one (B, F) float32 block, plus its contact geoms.

    A jitted call takes each host array on its own; one block instead of twelve arrays made the env's progress update
    about 10 us faster per call at batch 1 on this 2-core CPU (docs/benchmarks.md, the PyBullet section).
    """

    floats: np.ndarray
    contact_geom: np.ndarray
    shapes: tuple = struct.field(pytree_node=False)
    """Each float field's shape after the batch dimension, in `_BLOCK_FIELDS` order."""

    @classmethod
    def pack(cls, state: SceneState) -> HostBlock:
        arrays = [getattr(state, name) for name in _BLOCK_FIELDS]
        batch = state.batch_size
        floats = np.concatenate([a.reshape(batch, -1) for a in arrays], axis=1, dtype=np.float32)
        return cls(floats, state.contact_geom, tuple(a.shape[1:] for a in arrays))

    def unpack(self) -> SceneState:
        fields, start = {}, 0
        for name, shape in zip(_BLOCK_FIELDS, self.shapes):
            size = int(np.prod(shape, dtype=int))
            fields[name] = self.floats[:, start:start + size].reshape(-1, *shape)
            start += size
        return SceneState(qpos=None, qvel=None, contact_geom=self.contact_geom, **fields)


def unpacked(data: SceneState | HostBlock) -> SceneState:
    """The SceneState of `for_jit`'s output (inside jitted functions)."""
    return data.unpack() if isinstance(data, HostBlock) else data


def select_rows(rows: np.ndarray, new, old):
    """Pytrees of batch-first arrays: the rows of `new` where `rows` (a (B,) bool mask) holds, else those of `old`.
    NumPy leaves stay NumPy (and keep their dtype); JAX leaves stay JAX."""

    def pick(n, o):
        xp = np if isinstance(n, np.ndarray) else jnp
        return xp.where(rows.reshape(rows.shape + (1,) * (n.ndim - 1)), n, o)

    return jax.tree.map(pick, new, old)


def empty_scene_state(batch_size: int, nq: int, nv: int, nbody: int) -> SceneState:
    """A zero-filled host-side SceneState used as the backends' output buffer."""
    b, k = batch_size, MAX_FINGER_CONTACTS
    return SceneState(
        time=np.zeros(b),
        qpos=np.zeros((b, nq)),
        qvel=np.zeros((b, nv)),
        arm_qpos=np.zeros((b, 7)),
        finger_qpos=np.zeros((b, 2)),
        tcp_pos=np.zeros((b, 3)),
        tcp_quat=np.zeros((b, 4)),
        object_pos=np.zeros((b, 3)),
        object_quat=np.zeros((b, 4)),
        body_pos=np.zeros((b, body_rows(nbody), 3)),
        body_quat=np.tile([1.0, 0.0, 0.0, 0.0], (b, body_rows(nbody), 1)),
        contact_pos=np.zeros((b, 2, k, 3)),
        contact_force=np.zeros((b, 2, k)),
        contact_geom=np.full((b, 2, k), -1, dtype=np.int32),
    )
