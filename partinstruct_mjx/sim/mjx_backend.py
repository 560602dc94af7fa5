"""The `mjx` backend: a batch of MuJoCo XLA states stepped together (vmapped, jitted), for GPUs.

Same interface and the same SceneState as the `mujoco` backend; the state stays on the device. On a CPU it works
but is far slower than C MuJoCo (DESIGN.md): use it there only for short checks.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from partinstruct_mjx.errors import SceneError
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.mujoco_backend import initial_positions
from partinstruct_mjx.sim.scene import Scene
from partinstruct_mjx.sim.state import MAX_FINGER_CONTACTS, SceneState, body_rows, select_rows


class MjxBackend:
    """Steps B copies of a scene with MJX; `reset` and `step` return the batched SceneState (device arrays)."""

    def __init__(self, scene: Scene, batch_size: int):
        if batch_size < 1:
            raise SceneError(f"batch_size must be >= 1, got {batch_size}")
        self.scene = scene
        self.batch_size = batch_size
        self.model = put_model(scene.model)
        self._fresh = fresh_data(scene.model, self.model, batch_size)
        self.data = None
        self._indices = scene_indices(scene)

    def close(self) -> None:
        """Nothing to release (kept for interface parity with MujocoBackend)."""

    def reset(self, object_xy=None, object_quat=None, rows: np.ndarray | None = None) -> SceneState:
        """Robot at home, objects placed as given, then `settle_steps` control steps on the device (spec 1.4b).
        With a (B,) bool `rows`, only those environments take the new state; the others keep theirs."""
        qpos, act = initial_positions(self.scene, self.batch_size, object_xy, object_quat)
        ctrl = np.tile(panda.HOME_CTRL, (self.batch_size, 1))
        data = jax.vmap(lambda q, a, c: self._fresh.replace(qpos=q, act=a, ctrl=c))(
            jnp.asarray(qpos), jnp.asarray(act), jnp.asarray(ctrl))
        data = _forward(self.model, data)
        for _ in range(self.scene.config.settle_steps):
            data = _step(self.model, data, jnp.asarray(ctrl), self.scene.config.substeps)
        self.data = data if rows is None or self.data is None else select_rows(np.asarray(rows), data, self.data)
        return _extract(self.model, self.data, self._indices)

    def step(self, ctrl) -> SceneState:
        """Apply actuator targets (B, 8) for one control step."""
        ctrl = jnp.asarray(ctrl)
        if ctrl.shape != (self.batch_size, panda.NUM_CTRL):
            raise SceneError(f"ctrl must have shape ({self.batch_size}, {panda.NUM_CTRL}), got {ctrl.shape}")
        self.data = _step(self.model, self.data, ctrl, self.scene.config.substeps)
        return _extract(self.model, self.data, self._indices)

    def unstable(self) -> jnp.ndarray:
        """(B,) bool: the simulation diverged (a NaN or infinite joint position or velocity)."""
        return _diverged(self.data.qpos, self.data.qvel)

    def snapshot(self) -> mjx.Data:
        """The whole batch's physics state, for `restore` (MJX data is immutable: the snapshot is the data)."""
        return self.data

    def restore(self, snapshot: mjx.Data, rows: np.ndarray) -> SceneState:
        """Put the environments where the (B,) mask `rows` holds back to `snapshot`; the others go on unchanged."""
        self.data = select_rows(np.asarray(rows), snapshot, self.data)
        return _extract(self.model, self.data, self._indices)


@jax.jit
def _diverged(qpos, qvel) -> jnp.ndarray:
    return ~(jnp.isfinite(qpos).all(axis=-1) & jnp.isfinite(qvel).all(axis=-1))


def scene_indices(scene: Scene) -> dict:
    """The addresses `extract_state` reads (a pytree, so jitted functions take it as an argument)."""
    return {
        "arm": jnp.asarray(scene.arm_qpos_adr), "finger": jnp.asarray(scene.finger_qpos_adr),
        "tcp": scene.tcp_site, "hand": scene.hand_body, "object": scene.object_body,
        "geom_finger": jnp.asarray(scene.geom_finger),
    }


@jax.jit
def _forward(model, data):
    return jax.vmap(mjx.forward, in_axes=(None, 0))(model, data)


@partial(jax.jit, static_argnames="substeps")
def _step(model, data, ctrl, substeps: int):
    def one(d, c):
        d = d.replace(ctrl=c)
        return jax.lax.fori_loop(0, substeps, lambda _, x: mjx.step(model, x), d)

    return jax.vmap(one)(data, ctrl)


WARP_CONTACTS_PER_ENV = 96
WARP_ROWS_PER_ENV = 640
"""Warp preallocates: contact slots per environment in its shared contact buffer, and constraint rows per
environment (a contact takes 4 rows, 6 on the condim-4 finger pads)."""


def put_model(scene_model: mujoco.MjModel) -> mjx.Model:
    """The scene on the device, in the implementation MJX picks: JAX, or Warp on a CUDA GPU when the environment
    sets MJX_GPU_DEFAULT_WARP=true and warp-lang is installed. Warp would print a warning whenever the solver stops
    at its iteration caps, as the scene expects (C MuJoCo stops there silently): those two warnings are turned off;
    capacity overflows still warn."""
    model = mjx.put_model(scene_model)
    if model.impl != mjx.Impl.WARP:
        return model
    from mujoco.mjx.third_party.mujoco_warp._src.types import OverflowType

    options = model.opt._impl
    quiet = options.warn_overflow & ~(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)
    return model.replace(opt=model.opt.replace(_impl=options.replace(warn_overflow=int(quiet))))


def fresh_data(scene_model: mujoco.MjModel, model: mjx.Model, batch_size: int) -> mjx.Data:
    """One environment's initial mjx.Data for `model`'s implementation. Warp's contact buffer is shared by every
    environment stepped together, so it is sized for `batch_size` of them."""
    if model.impl == mjx.Impl.WARP:
        return mjx.make_data(scene_model, impl=model.impl, naconmax=WARP_CONTACTS_PER_ENV * batch_size,
                             njmax=WARP_ROWS_PER_ENV)
    return mjx.make_data(model)


def _normal_forces(efc_force, efc_address, condim) -> jnp.ndarray:
    """Normal force of every contact: the sum of its pyramid rows (pyramidal cones, as the scene uses)."""
    rows = jnp.where(condim == 1, 1, 2 * (condim - 1))
    width = 2 * (6 - 1)
    index = jnp.clip(efc_address[:, None] + jnp.arange(width), 0, efc_force.shape[0] - 1)
    used = (jnp.arange(width) < rows[:, None]) & (efc_address[:, None] >= 0)
    return jnp.where(used, efc_force[index], 0.0).sum(axis=1)


def _warp_contacts(d):
    """One environment's contacts on MuJoCo Warp, found through its own constraint rows.

    Warp keeps the contacts of all environments in one shared buffer (`contact__worldid` says whose), while the
    constraint rows are per environment, and a contact row's `efc__id` is the contact's index in that buffer: each
    contact is read once, at its first row, and its normal force is the sum of its pyramid rows."""
    impl = d._impl
    rows = jnp.arange(impl.efc__type.shape[0])
    contact = jnp.clip(impl.efc__id, 0, impl.contact__geom.shape[0] - 1)
    addresses = impl.contact__efc_address[contact]
    first = ((rows < impl.nefc) & (impl.efc__type == int(mujoco.mjtConstraint.mjCNSTR_CONTACT_PYRAMIDAL))
             & (addresses[:, 0] == rows))
    pyramid = jnp.where(addresses >= 0, impl.efc__force[jnp.clip(addresses, 0, rows.shape[0] - 1)], 0.0).sum(axis=1)
    return impl.contact__geom[contact], impl.contact__pos[contact], jnp.where(first, pyramid, 0.0)


def contacts(d) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """One environment's contact slots: geom pairs (N, 2), positions (N, 3) and normal forces (N,); slots that
    hold no contact have force 0. MJX's JAX and Warp implementations store contacts differently."""
    if d.impl == mjx.Impl.WARP:
        return _warp_contacts(d)
    contact = d._impl.contact
    return contact.geom, contact.pos, _normal_forces(d._impl.efc_force, contact.efc_address, contact.dim)


@jax.jit
def _extract(model, data, indices) -> SceneState:
    return jax.vmap(extract_state, in_axes=(None, 0, None))(model, data, indices)


def _padded_bodies(rows, first):
    """Body rows padded to `body_rows` (origin / identity quaternion: `first` in column 0)."""
    extra = body_rows(rows.shape[0]) - rows.shape[0]
    padding = jnp.zeros((extra, rows.shape[1]), rows.dtype).at[:, 0].set(first)
    return jnp.concatenate([rows, padding])


def extract_state(model, d, indices) -> SceneState:
    """One environment's SceneState from its mjx.Data (the same fields the mujoco backend fills)."""
    geom, pos, forces = contacts(d)
    finger = indices["geom_finger"][geom]
    slots = []
    for side in (0, 1):
        on_finger = finger == side
        touches = on_finger.any(axis=1) & (forces > 0)
        other = jnp.where(on_finger[:, 0], geom[:, 1], geom[:, 0])
        score, index = jax.lax.top_k(jnp.where(touches, forces, -1.0), MAX_FINGER_CONTACTS)
        used = score > 0
        slots.append((jnp.where(used[:, None], pos[index], 0.0), jnp.where(used, score, 0.0),
                      jnp.where(used, other[index], -1).astype(jnp.int32)))
    return SceneState(
        time=d.time, qpos=d.qpos, qvel=d.qvel,
        arm_qpos=d.qpos[indices["arm"]], finger_qpos=d.qpos[indices["finger"]],
        tcp_pos=d.site_xpos[indices["tcp"]], tcp_quat=d.xquat[indices["hand"]],
        object_pos=d.xpos[indices["object"]], object_quat=d.xquat[indices["object"]],
        body_pos=_padded_bodies(d.xpos, 0.0), body_quat=_padded_bodies(d.xquat, 1.0),
        contact_pos=jnp.stack([s[0] for s in slots]), contact_force=jnp.stack([s[1] for s in slots]),
        contact_geom=jnp.stack([s[2] for s in slots]),
    )
