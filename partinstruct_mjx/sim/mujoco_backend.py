"""The `mujoco` backend: a batch of C-MuJoCo MjData stepped in parallel on CPU threads.

MuJoCo releases the GIL inside `mj_step`, so a thread pool scales with cores. Each worker steps a fixed chunk of
environments and copies their state into preallocated batch arrays, so results do not depend on the thread count:
stepping B environments together gives exactly the states of stepping them one by one.
"""

from __future__ import annotations

import copy
import os
from concurrent.futures import ThreadPoolExecutor

import mujoco
import numpy as np

from partinstruct_mjx.errors import SceneError
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import TABLE_HEIGHT, Scene
from partinstruct_mjx.sim.state import MAX_FINGER_CONTACTS, SceneState, empty_scene_state

DROP_CLEARANCE = 0.005
"""Height of the object's lowest point above the table when it is released at reset."""

_PHYSICS_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
_BAD_VALUE_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL,
                       mujoco.mjtWarning.mjWARN_BADQACC)
"""MuJoCo's warnings of a diverged simulation, after which it resets the MjData to the model's defaults."""


class MujocoBackend:
    """Steps B copies of a scene with C MuJoCo; `reset` and `step` return the batched SceneState."""

    def __init__(self, scene: Scene, batch_size: int, num_threads: int | None = None):
        if batch_size < 1:
            raise SceneError(f"batch_size must be >= 1, got {batch_size}")
        self.scene = scene
        self.model = scene.model
        self.batch_size = batch_size
        self.datas = [mujoco.MjData(self.model) for _ in range(batch_size)]
        threads = max(1, min(num_threads or os.cpu_count() or 1, batch_size))
        self._chunks = [c for c in np.array_split(np.arange(batch_size), threads) if len(c)]
        self._pool = ThreadPoolExecutor(threads) if threads > 1 else None
        m = self.model
        self._state = empty_scene_state(batch_size, m.nq, m.nv, m.nbody)
        self._ctrl = np.tile(panda.HOME_CTRL, (batch_size, 1))
        self._force6 = [np.zeros(6) for _ in range(batch_size)]
        self._unstable = np.zeros(batch_size, bool)
        self._split = scene.config.contact_split
        self._fine_model = copy.copy(self.model)
        self._fine_model.opt.timestep = self.model.opt.timestep / self._split

    @property
    def control_dt(self) -> float:
        return self.scene.config.control_dt

    def close(self) -> None:
        """Stop the worker threads."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __enter__(self) -> MujocoBackend:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def reset(self, object_xy: np.ndarray | None = None, object_quat: np.ndarray | None = None,
              rows: np.ndarray | None = None) -> SceneState:
        """Put the robot at home, drop the object at (x, y) with orientation `object_quat` and let it settle.

        Args:
          object_xy: (B, 2) object positions on the table; default (0, -0.03) (spec 1.4 example poses).
          object_quat: (B, 4) object orientations (w, x, y, z); default identity.
          rows: (B,) bool: reset only these environments (the others are neither reset nor stepped); default all.
        Returns:
          The SceneState after `config.settle_steps` control steps with the robot held at home (spec 1.4b).
        """
        qpos, act = initial_positions(self.scene, self.batch_size, object_xy, object_quat)
        chosen = np.arange(self.batch_size) if rows is None else np.flatnonzero(rows)
        for i in chosen:
            data = self.datas[i]
            mujoco.mj_resetData(self.model, data)
            data.qpos[:], data.act[:], data.ctrl[:] = qpos[i], act[i], panda.HOME_CTRL
            mujoco.mj_forward(self.model, data)
        self._ctrl[chosen] = panda.HOME_CTRL
        for _ in range(self.scene.config.settle_steps):
            self._run(self._step_chunk, chosen)
        return self._run(self._extract_chunk)

    def step(self, ctrl: np.ndarray, rows: np.ndarray | None = None) -> SceneState:
        """Apply actuator targets (B, 8) = 7 arm joint angles + finger opening for one control step; with a (B,)
        mask `rows`, only to those environments (the others are not stepped and keep their state).

        The returned SceneState's arrays are the backend's reusable buffers: the next `step`, `reset` or
        `set_physics_state` overwrites them, so a caller that keeps an earlier state copies what it keeps (JAX calls
        copy their inputs at dispatch; the oracle's recording and the evaluator's videos copy).
        """
        ctrl = np.asarray(ctrl, dtype=float)
        if ctrl.shape != (self.batch_size, panda.NUM_CTRL):
            raise SceneError(f"ctrl must have shape ({self.batch_size}, {panda.NUM_CTRL}), got {ctrl.shape}")
        np.copyto(self._ctrl, ctrl)
        return self._run(self._step_and_extract_chunk, None if rows is None else np.flatnonzero(rows))

    def get_physics_state(self) -> np.ndarray:
        """(B, nstate) MuJoCo integration state (time, qpos, qvel, act, warm start, ctrl ...) for exact replay."""
        size = mujoco.mj_stateSize(self.model, _PHYSICS_STATE)
        out = np.empty((self.batch_size, size))
        for i, data in enumerate(self.datas):
            mujoco.mj_getState(self.model, data, out[i], _PHYSICS_STATE)
        return out

    def set_physics_state(self, states: np.ndarray, rows: np.ndarray | None = None) -> SceneState:
        """Restore states from `get_physics_state` (only the environments where the (B,) mask `rows` holds, if
        given) and return the matching SceneState."""
        states = np.asarray(states, dtype=float)
        size = mujoco.mj_stateSize(self.model, _PHYSICS_STATE)
        if states.shape != (self.batch_size, size):
            raise SceneError(f"physics states must have shape ({self.batch_size}, {size}), got {states.shape}")
        for i in range(self.batch_size) if rows is None else np.flatnonzero(rows):
            data = self.datas[i]
            for warning in _BAD_VALUE_WARNINGS:
                data.warning[warning].number = 0
            mujoco.mj_setState(self.model, data, states[i], _PHYSICS_STATE)
            mujoco.mj_forward(self.model, data)
            self._ctrl[i] = data.ctrl
        return self._run(self._extract_chunk)

    def unstable(self) -> np.ndarray:
        """(B,) bool: the simulation diverged (NaN or huge values) since the scene's reset or restore. MuJoCo then
        warns and resets the scene's MjData to the model's defaults, so what follows is not the episode's physics."""
        return self._unstable.copy()

    def snapshot(self) -> np.ndarray:
        """The whole batch's physics state, for `restore` (the same as `get_physics_state`)."""
        return self.get_physics_state()

    def restore(self, snapshot: np.ndarray, rows: np.ndarray) -> SceneState:
        """Put the environments where the (B,) mask `rows` holds back to `snapshot`; the others go on unchanged."""
        return self.set_physics_state(snapshot, rows)

    # --- workers -------------------------------------------------------------------------------------------

    def _run(self, work, only: np.ndarray | None = None) -> SceneState:
        """`work` on every environment (or on those in `only`), each thread on its fixed chunk."""
        chunks = self._chunks if only is None else [c[np.isin(c, only)] for c in self._chunks]
        if self._pool is None:
            work(chunks[0])
        else:
            for future in [self._pool.submit(work, chunk) for chunk in chunks if len(chunk)]:
                future.result()
        return self._state.replace()

    def _step_chunk(self, envs: np.ndarray) -> None:
        nstep = self.scene.config.substeps
        for i in envs:
            data = self.datas[i]
            data.ctrl[:] = self._ctrl[i]
            if self._split > 1 and self._pads_touch(data):
                mujoco.mj_step(self._fine_model, data, nstep=self._split * nstep)
            else:
                mujoco.mj_step(self.model, data, nstep=nstep)

    def _pads_touch(self, data: mujoco.MjData) -> bool:
        """A finger geom is in one of the contacts of the last physics step (`SceneConfig.contact_split`)."""
        return bool((self.scene.geom_finger[data.contact.geom[: data.ncon]] >= 0).any())

    def _step_and_extract_chunk(self, envs: np.ndarray) -> None:
        self._step_chunk(envs)
        self._extract_chunk(envs)

    def _extract_chunk(self, envs: np.ndarray) -> None:
        for i in envs:
            self._extract(i)

    def _extract(self, i: int) -> None:
        """Copy environment i's MjData into row i of the batch state."""
        data, scene, out = self.datas[i], self.scene, self._state
        out.time[i] = data.time
        out.qpos[i] = data.qpos
        out.qvel[i] = data.qvel
        out.arm_qpos[i] = data.qpos[scene.arm_qpos_adr]
        out.finger_qpos[i] = data.qpos[scene.finger_qpos_adr]
        out.tcp_pos[i] = data.site_xpos[scene.tcp_site]
        out.tcp_quat[i] = data.xquat[scene.hand_body]
        out.object_pos[i] = data.xpos[scene.object_body]
        out.object_quat[i] = data.xquat[scene.object_body]
        out.body_pos[i, : self.model.nbody] = data.xpos
        out.body_quat[i, : self.model.nbody] = data.xquat
        self._unstable[i] = any(data.warning[warning].number for warning in _BAD_VALUE_WARNINGS)
        self._extract_finger_contacts(i)

    def _extract_finger_contacts(self, i: int) -> None:
        data, out = self.datas[i], self._state
        out.contact_pos[i] = 0.0
        out.contact_force[i] = 0.0
        out.contact_geom[i] = -1
        if data.ncon == 0:
            return
        geoms = data.contact.geom[: data.ncon]
        finger_of = self.scene.geom_finger[geoms]
        found: list[list[tuple[float, int, int]]] = [[], []]
        for c in np.flatnonzero((finger_of >= 0).any(axis=1)):
            side = 0 if finger_of[c, 0] >= 0 else 1
            mujoco.mj_contactForce(self.model, data, int(c), self._force6[i])
            found[finger_of[c, side]].append((self._force6[i][0], int(c), int(geoms[c, 1 - side])))
        for finger, contacts in enumerate(found):
            contacts.sort(key=lambda item: -item[0])
            for slot, (force, c, other) in enumerate(contacts[:MAX_FINGER_CONTACTS]):
                out.contact_pos[i, finger, slot] = data.contact.pos[c]
                out.contact_force[i, finger, slot] = force
                out.contact_geom[i, finger, slot] = other


def initial_positions(scene: Scene, batch_size: int, object_xy=None, object_quat=None) -> tuple[np.ndarray, np.ndarray]:
    """(B, nq) joint positions and (B, na) actuator states at reset, before settling (spec 1.4b).

    Robot at home with the gripper open; the object at (x, y) (default (0, -0.03)) with orientation (w, x, y, z)
    (default identity), its lowest point DROP_CLEARANCE above the table.
    """
    model = scene.model
    xy = np.broadcast_to(np.asarray([0.0, -0.03]) if object_xy is None else np.asarray(object_xy, float),
                         (batch_size, 2))
    quat = np.broadcast_to([1.0, 0, 0, 0] if object_quat is None else np.asarray(object_quat, float), (batch_size, 4))
    data = mujoco.MjData(model)
    qpos, act = np.zeros((batch_size, model.nq)), np.zeros((batch_size, model.na))
    adr = scene.object_qpos_adr
    for i in range(batch_size):
        data.qpos[:] = model.qpos0
        data.qpos[scene.arm_qpos_adr] = panda.HOME_ARM_QPOS
        data.qpos[scene.finger_qpos_adr] = panda.FINGER_OPEN
        data.qpos[adr:adr + 7] = [xy[i, 0], xy[i, 1], 0.0, *(quat[i] / np.linalg.norm(quat[i]))]
        mujoco.mj_kinematics(model, data)
        data.qpos[adr + 2] = TABLE_HEIGHT + DROP_CLEARANCE - object_z_range(scene, data)[0]
        qpos[i] = data.qpos
        act[i, model.actuator(panda.GRIPPER_ACTUATOR).actadr[0]] = panda.FINGER_OPEN
    return qpos, act


def object_z_range(scene: Scene, data: mujoco.MjData) -> tuple[float, float]:
    """Lowest and highest world z of the object's collision geoms (from their bounding boxes) in `data`."""
    geoms = scene.object_geoms
    rot = data.geom_xmat[geoms].reshape(-1, 3, 3)
    centre_z = data.geom_xpos[geoms, 2] + np.einsum("gj,gj->g", rot[:, 2], scene.model.geom_aabb[geoms, :3])
    half_z = np.einsum("gj,gj->g", np.abs(rot[:, 2]), scene.model.geom_aabb[geoms, 3:])
    return float((centre_z - half_z).min()), float((centre_z + half_z).max())
