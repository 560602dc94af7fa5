"""The batched PartInstruct environment: reset(key, episodes) -> State, step(State, action) -> State.

One environment object drives B scenes of the same object (MJX needs one model per batch) on a physics backend
('mujoco': C MuJoCo on CPU threads; 'mjx': MuJoCo XLA). Actions are the original's absolute TCP poses (spec 1.6):
xyz + Euler 'xyz' (or a quaternion) + the finger opening in metres; a batched JAX IK turns them into joint targets.
Success follows the episode's skill chain (skill mode, the evaluation default) or its task goals (task mode).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from partinstruct_mjx.control import jax_ik
from partinstruct_mjx.control.rotations import euler_xyz_to_quat, quat_to_euler_xyz
from partinstruct_mjx.errors import SceneError, TaskError
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import SceneConfig, build_scene
from partinstruct_mjx.sim.state import HostBlock, SceneState, select_rows, unpacked
from partinstruct_mjx.tasks import progress
from partinstruct_mjx.tasks.part_geometry import load_parts

STEP_LIMIT = 250
STEP_LIMIT_TEST4 = 400
"""Evaluation horizons in env steps (spec 9.4)."""


def step_limit(split: str) -> int:
    """A split's episode horizon: STEP_LIMIT_TEST4 for test4, STEP_LIMIT for the others."""
    return STEP_LIMIT_TEST4 if split == "test4" else STEP_LIMIT


@dataclass(frozen=True)
class EnvConfig:
    """Environment settings.

    Attributes:
      backend: 'mujoco' (C MuJoCo on CPU threads) or 'mjx'.
      skill_mode: success = the ground-truth skill chain completed (evaluation default) instead of the task goals.
      rotation: 'euler' (7-D actions, the original's) or 'quat' (8-D: xyz, quaternion w x y z, finger).
      object_noise: metres of uniform noise the reset key adds to each object's x and y (0 = exact poses).
    """

    backend: str = "mujoco"
    skill_mode: bool = True
    rotation: str = "euler"
    object_noise: float = 0.0
    ik: jax_ik.IKConfig = jax_ik.IKConfig()
    scene: SceneConfig = field(default_factory=SceneConfig)
    num_threads: int | None = None

    def __post_init__(self):
        if self.backend not in ("mujoco", "mjx"):
            raise SceneError(f"unknown backend '{self.backend}'; expected 'mujoco' or 'mjx'")
        if self.rotation not in ("euler", "quat"):
            raise SceneError(f"unknown rotation '{self.rotation}'; expected 'euler' or 'quat'")

    @property
    def action_size(self) -> int:
        return 7 if self.rotation == "euler" else 8


@struct.dataclass
class State:
    """Brax/Playground-style environment state of a batch (leading dimension B everywhere)."""

    data: SceneState
    task: progress.TaskState
    obs: dict[str, Any]
    reward: jnp.ndarray
    done: jnp.ndarray
    metrics: dict[str, Any]
    info: dict[str, Any]


_BUILD_LOCK = threading.Lock()
"""Envs are built one at a time (worker threads build theirs; MuJoCo's XML compiler is not known to be
thread-safe)."""


class PartInstructEnv:
    """B scenes of one object; the episodes given at reset choose each scene's pose and task."""

    def __init__(self, object_xml: str | Path, batch_size: int, config: EnvConfig = EnvConfig()):
        self.config = config
        with _BUILD_LOCK:
            self.scene = build_scene(replace(config.scene, object_xml=str(object_xml)))
            self.geometry, self.part_names = load_parts(self.scene)
        self.batch_size = batch_size
        self.kinematics = jax_ik.ArmKinematics.from_scene(self.scene)
        if config.backend == "mujoco":
            from partinstruct_mjx.sim.mujoco_backend import MujocoBackend

            self.backend = MujocoBackend(self.scene, batch_size, config.num_threads)
        else:
            from partinstruct_mjx.sim.mjx_backend import MjxBackend

            self.backend = MjxBackend(self.scene, batch_size)
        self.episodes: list = []
        self._target_rows = np.full((batch_size, progress.MAX_SKILLS), -1, np.int32)
        self._surface = None
        self._renderer = None

    def close(self) -> None:
        self.backend.close()
        if self._renderer is not None:
            self._renderer.close()

    def __enter__(self) -> PartInstructEnv:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def reset(self, key: jax.Array, episodes: list) -> State:
        """Place each scene's object as its episode says (plus `object_noise` drawn from `key`), settle, start tasks.

        `episodes` are `partinstruct_mjx.tasks.episodes.Episode`s (obj_pose is [qx, qy, qz, qw, x, y, z]).
        """
        if len(episodes) != self.batch_size:
            raise TaskError(f"reset needs {self.batch_size} episodes, got {len(episodes)}")
        return self._start(key, list(episodes))

    def reset_rows(self, state: State, key: jax.Array, rows, episodes: list) -> State:
        """Start `episodes` in the scenes where the (B,) mask `rows` holds, in row order, as `reset` would; the
        other scenes go on unchanged (they are not stepped meanwhile). For streaming many episodes through B scenes."""
        rows = np.asarray(rows, bool)
        if rows.shape != (self.batch_size,) or len(episodes) != rows.sum():
            raise TaskError(f"reset_rows needs a ({self.batch_size},) row mask and one episode per chosen row, got "
                            f"{rows.shape} and {len(episodes)} episodes")
        full = list(self.episodes)
        for b, episode in zip(np.flatnonzero(rows), episodes):
            full[b] = episode
        return self._start(key, full, rows, state)

    def _start(self, key: jax.Array, episodes: list, rows: np.ndarray | None = None, old: State | None = None) -> State:
        """Reset the scenes of `rows` (all if None) to their entries of `episodes` (one per scene)."""
        compiled = progress.compile_episodes([(e.task_type, list(e.chain)) for e in episodes], self.part_names)
        poses = np.array([e.obj_pose for e in episodes], dtype=float)
        if poses.shape != (self.batch_size, 7):
            raise TaskError(f"obj_pose must be [qx, qy, qz, qw, x, y, z]; got shape {poses.shape[1:]}")
        noise = self.config.object_noise * jax.random.uniform(key, (self.batch_size, 2), minval=-1.0, maxval=1.0)
        xy = poses[:, 4:6] + np.asarray(noise)
        quat = np.concatenate([poses[:, 3:4], poses[:, :3]], axis=1)
        data = self.backend.reset(xy, quat, rows)
        self.episodes = episodes
        self._target_rows[:] = -1
        for b, episode in enumerate(episodes):
            for s, step in enumerate(episode.chain):
                if step.part is not None:
                    self._target_rows[b, s] = self.part_names.index(step.part)
        task = _initial(data.for_jit(), self.geometry, compiled)
        limits = np.array([step_limit(e.split) for e in episodes], np.int32)
        info = {"steps": jnp.zeros(self.batch_size, jnp.int32), "step_limit": jnp.asarray(limits),
                "truncated": jnp.zeros(self.batch_size, bool), "unstable": jnp.zeros(self.batch_size, bool),
                "joint_targets": jnp.asarray(data.arm_qpos, jnp.float32)}
        if old is not None:
            task, info = select_rows(rows, (task, info), (old.task, old.info))
        return _assemble(data, task, info, _outputs(data.for_jit(), task, info))

    def step(self, state: State, action, active=None) -> State:
        """Apply one (B, 7) Euler or (B, 8) quaternion action to every scene for one 20 Hz step.

        active: (B,) bool, the scenes whose outcome the caller still reads (default all). The `mujoco` backend does
        not simulate the others (their physics stays as it was; their returned state is not meaningful); `mjx` steps
        the whole batch as one program either way."""
        # A host action stays on the host until the IK's dispatch copies it (an eager conversion costs as much).
        action = jnp.asarray(action, jnp.float32) if isinstance(action, jax.Array) else np.asarray(action, np.float32)
        if action.shape != (self.batch_size, self.config.action_size):
            raise TaskError(f"action must have shape ({self.batch_size}, {self.config.action_size}) for "
                            f"rotation='{self.config.rotation}', got {tuple(action.shape)}")
        ctrl = joint_targets(self.kinematics, self.config.ik, state.info["joint_targets"], action)
        if self.config.backend == "mujoco":
            data = self.backend.step(np.asarray(ctrl), None if active is None else np.asarray(active, bool))
        else:
            data = self.backend.step(ctrl)
        changed, info, outputs = _advance(state.task, state.info, state.done, data.for_jit(), self.geometry, ctrl,
                                          self.backend.unstable(), self.config.skill_mode)
        return _assemble(data, state.task.replace(**changed), {**state.info, **info}, outputs)

    def instructions(self, state: State) -> list[str]:
        """The instruction each scene's policy sees now: the current skill's (skill mode) or the task's."""
        if not self.config.skill_mode:
            return [e.task_instruction for e in self.episodes]
        index = np.minimum(np.asarray(state.task.skill_index), [len(e.chain) - 1 for e in self.episodes])
        return [e.skill_instructions[i] for e, i in zip(self.episodes, index)]

    def target_parts(self, state: State) -> np.ndarray:
        """(B,) part row of each scene's current target (the current skill's part, spec 2.1; -1 for move/release
        and in task mode)."""
        if not self.config.skill_mode:
            return np.full(self.batch_size, -1, np.int32)
        index = np.minimum(np.asarray(state.task.skill_index), progress.MAX_SKILLS - 1)
        return self._target_rows[np.arange(self.batch_size), index]

    def point_clouds(self, state: State, key: jax.Array, sampler: str = "fps") -> dict[str, jnp.ndarray]:
        """Batched static-camera clouds from the JAX point renderer (no OpenGL): agentview_pcd (B, 1024, 3) in the
        camera's optical frame, agentview_pcd_world, and agentview_part_pcd (B, 1024, 4) with the target column."""
        from partinstruct_mjx.obs import point_renderer
        from partinstruct_mjx.obs.cameras import AGENTVIEW, scene_camera

        if self._surface is None:
            self._surface = (point_renderer.surface_points(self.scene, self.geometry), scene_camera(self.scene, AGENTVIEW))
        surface, camera = self._surface
        parts = jnp.asarray(self.target_parts(state))
        masks = jax.vmap(point_renderer.target_mask, in_axes=(None, None, 0, 0))(surface, self.geometry,
                                                                                 state.task.masks, parts)
        cloud = point_renderer.render_batch(surface, camera, jnp.asarray(state.data.body_pos),
                                            jnp.asarray(state.data.body_quat), masks,
                                            jax.random.split(key, self.batch_size), sampler=sampler)
        return {"agentview_pcd": cloud.points, "agentview_pcd_world": cloud.world,
                "agentview_part_pcd": jnp.concatenate([cloud.points, cloud.target[..., None]], axis=-1)}

    def camera_observations(self, state: State, wrist: bool = False) -> list[dict[str, np.ndarray]]:
        """Per scene, the OpenGL observations of spec 2.1 (RGB, part mask, depth clouds, optionally the wrist
        camera); see `obs.depth_cloud.camera_observations`. Needs an OpenGL context (MUJOCO_GL=egl headless)."""
        from partinstruct_mjx.obs.depth_cloud import camera_observations
        from partinstruct_mjx.obs.images import ImageRenderer

        if self._renderer is None:
            self._renderer = ImageRenderer(self.scene, parts=(self.geometry, self.part_names))
        parts = self.target_parts(state)
        return [camera_observations(self._renderer, jax.tree_util.tree_map(lambda x: x[b], state.data),
                                    None if parts[b] < 0 else int(parts[b]), state.task.masks[b], wrist)
                for b in range(self.batch_size)]


@jax.jit
def _initial(data: SceneState | HostBlock, geometry, compiled: dict) -> progress.TaskState:
    return progress.initial_task_state(unpacked(data), geometry, compiled)


@jax.jit(static_argnames="skill_mode")
def _advance(task, info: dict, done, data: SceneState | HostBlock, geometry, ctrl, unstable, skill_mode: bool):
    """Everything of a step after physics in one dispatch. Returns only what changes (every returned array costs
    time at batch 1): the `progress.PROGRESS_FIELDS` of the task, the changed info and `_outputs`.

    A scene whose simulation diverged (`unstable`, the backend's) ends without success, truncated, and stays so."""
    data = unpacked(data)
    task = progress.update(task, data, geometry, skill_mode=skill_mode)
    unstable = info["unstable"] | unstable
    task = task.replace(success=task.success & ~unstable)
    steps = info["steps"] + ~done
    info = {"steps": steps, "truncated": ~task.success & (steps >= info["step_limit"]) | unstable,
            "unstable": unstable, "joint_targets": ctrl[:, :7]}
    changed = {name: getattr(task, name) for name in progress.PROGRESS_FIELDS}
    return changed, info, _outputs(data, task, info)


@jax.jit
def _outputs(data: SceneState | HostBlock, task: progress.TaskState, info: dict) -> dict:
    """The arrays of a State that are computed from the task state and info rather than copied from them."""
    data = unpacked(data)
    return {"obs": observe(data, task), "reward": task.success.astype(jnp.float32),
            "done": task.success | info["truncated"],
            "goals": {f"goal_{g}": task.goals_met[:, g] for g in range(progress.MAX_GOALS)}}


def _assemble(data: SceneState, task: progress.TaskState, info: dict, outputs: dict) -> State:
    """The State of `data`, `task`, `info` and their `_outputs` (no JAX dispatch)."""
    metrics = {"success": task.success, "completion": task.completion, "skill_index": task.skill_index,
               "phase": task.phase, **outputs["goals"]}
    return State(data=data, task=task, obs=outputs["obs"],
                 reward=outputs["reward"], done=outputs["done"], metrics=metrics, info=info)


def hold_action(tcp_pose, finger: float = panda.FINGER_OPEN) -> np.ndarray:
    """(B, 7) Euler actions that keep the TCP at an observed `tcp_pose` (B, 7) [qx, qy, qz, qw, x, y, z]."""
    pose = np.asarray(tcp_pose)
    euler = np.asarray(quat_to_euler_xyz(jnp.asarray(np.roll(pose[:, :4], 1, axis=1))))
    return np.concatenate([pose[:, 4:], euler, np.full((len(pose), 1), finger)], axis=1)


def original_pose(quat, pos):
    """(B, 7) poses in the original's layout [qx, qy, qz, qw, x, y, z] from MuJoCo's (w, x, y, z) and positions."""
    quat = jnp.asarray(quat, jnp.float32)
    return jnp.concatenate([quat[:, 1:], quat[:, :1], jnp.asarray(pos, jnp.float32)], axis=1)


@jax.jit
def observe(data: SceneState, task: progress.TaskState) -> dict:
    """Proprioception in the original's layout (spec 2.1) and the index of the current instruction."""
    return {
        "tcp_pose": original_pose(data.tcp_quat, data.tcp_pos),
        "joint_states": jnp.asarray(data.arm_qpos, jnp.float32),
        "gripper_state": jnp.asarray(data.finger_qpos[:, :1], jnp.float32),
        "instruction_index": task.skill_index,
    }


@jax.jit(static_argnames="config")
def joint_targets(kinematics, config, arm_qpos, action):
    """IK of the pose part of the action, seeded from the previous joint targets; the finger target is clipped.

    Seeding from the measured joints (as the original does) lets the solution creep along the arm's redundant
    self-motion while the arm lags its targets, and the servos then chase it (measured: 2.8 cm TCP drift in 2 s
    holding a fixed pose). The previous targets are a fixed point for a fixed pose.
    """
    if action.shape[1] == 7:
        target_quat = euler_xyz_to_quat(action[:, 3:6])
    else:
        target_quat = action[:, 3:7] / jnp.linalg.norm(action[:, 3:7], axis=1, keepdims=True)
    q, _, _ = jax_ik.solve_ik(kinematics, arm_qpos, action[:, :3], target_quat, config)
    finger = jnp.clip(action[:, -1:], panda.FINGER_CLOSED, panda.FINGER_OPEN)
    return jnp.concatenate([q, finger], axis=1)
