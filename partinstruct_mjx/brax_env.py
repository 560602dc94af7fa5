"""PartInstruct as a `brax.envs.Env` on MJX: one pure, jittable environment for Brax's wrappers and brax.training.

`PartInstructEnv` (env.py) drives a batch and keeps its backend in Python objects; this class is its single-
environment, functional counterpart: `reset(rng)` and `step(state, action)` touch nothing but their arguments, so
`brax.envs.wrappers.training.wrap` (vmap, episode limit, auto-reset) and the brax.training agents work with it.

Everything that needs the host is done once at construction: the scene, the part geometry, the arm kinematics, the
goals of every episode, and every episode's settled initial state (the C backend, exactly as
`PartInstructEnv(backend="mujoco").reset` settles it). `reset` only picks one of those states.

    env = BraxPartInstructEnv("assets_mjcf/objects/mug/mug_000/object.xml", episodes)
    env = brax.envs.wrappers.training.wrap(env, episode_length=env.episode_length)
    state = jax.jit(env.reset)(jax.random.split(key, 64))
    state = jax.jit(env.step)(state, actions)                  # (64, 7)

Requires brax (`pip install brax`).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State
from flax import struct
from mujoco import mjx

from partinstruct_mjx.control import jax_ik
from partinstruct_mjx.env import EnvConfig, joint_targets, observe, step_limit
from partinstruct_mjx.errors import SceneError, TaskError
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.mjx_backend import extract_state, fresh_data, put_model, scene_indices
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
from partinstruct_mjx.sim.scene import build_scene
from partinstruct_mjx.sim.state import SceneState
from partinstruct_mjx.tasks import progress
from partinstruct_mjx.tasks.part_geometry import load_parts

OBS_LAYOUT = (("tcp_pose", 7), ("joint_states", 7), ("gripper_state", 1), ("skill_one_hot", progress.MAX_SKILLS))
"""Name and width of each block of the flat observation, in order."""
OBSERVATION_SIZE = sum(width for _, width in OBS_LAYOUT)


@struct.dataclass
class PipelineState:
    """Everything one environment carries between steps (no batch dimension; VmapWrapper adds one).

    Brax's AutoResetWrapper restores `pipeline_state` (and `obs`) of a finished environment but leaves `info` as it
    is, so all state that must start over with a new episode lives here: the physics, the task progress, the joint
    targets that seed the next IK solve and the step counter.

    Attributes:
      data: the MJX physics state.
      scene: the SceneState (the backends' layout) extracted from `data` after the last step.
      task: the episode's progress (`progress.TaskState`).
      joint_targets: (7,) arm joint targets of the last step (the IK seed; the settled joints after reset).
      episode: () index into the environment's episode list.
      steps: () environment steps since reset.
    """

    data: mjx.Data
    scene: SceneState
    task: progress.TaskState
    joint_targets: jnp.ndarray
    episode: jnp.ndarray
    steps: jnp.ndarray


class BraxPartInstructEnv(Env):
    """A single PartInstruct environment on MJX implementing `brax.envs.base.Env`; episodes of one object.

    `reset(rng)` draws one of `episodes` uniformly from `rng` and starts it from its pre-settled state (the object
    placed as the episode says and settled for `config.scene.settle_steps` control steps by C MuJoCo, at
    construction). `step(state, action)` runs one 20 Hz control step: IK of the pose action seeded from the
    previous joint targets, finger target clipped to [0, 0.04] m, `config.scene.substeps` MJX physics steps, then
    the skill-chain (skill mode) or task-goal (task mode) progress update, as `PartInstructEnv` does.

    Actions: (7,) xyz (m), Euler 'xyz' (rad), finger opening (m); (8,) with `EnvConfig(rotation="quat")`: xyz,
    quaternion (w, x, y, z), finger opening.

    Observation: a flat float32 vector of OBSERVATION_SIZE = 22 values:
      [0:7]   tcp_pose: TCP orientation and position [qx, qy, qz, qw, x, y, z] (the original's layout)
      [7:14]  joint_states: the seven arm joint angles (rad)
      [14:15] gripper_state: one finger's opening (m, 0 closed ... 0.04 open)
      [15:22] one-hot of the current skill index (MAX_SKILLS = 7 slots; the last skill's slot once the chain is
              done). In task mode the skill index does not advance, so slot 0 stays set.

    State: `reward` = success as float32 (sparse), `done` = success as float32; the step limit (250, 400 for
    test4) is left to Brax's EpisodeWrapper: pass `env.episode_length`. `metrics` (float32): success, completion,
    skill_index, phase, goal_0..goal_3 (the current skill's or phase's predicates). `pipeline_state` is a
    `PipelineState` (the source of truth); `info` mirrors its `episode`, `joint_targets` and `steps` (as
    'env_steps', since EpisodeWrapper owns 'steps'). Like all of `info` under AutoResetWrapper, the mirrors of the
    step that finished an episode still describe that episode; the next step reports the new one.

    Args:
      object_xml: the object's MJCF; every episode must be of this object (its folder name is the obj_id).
      episodes: `partinstruct_mjx.tasks.episodes.Episode`s; at least one.
      config: EnvConfig with backend 'mjx' (the default here); object_noise must be 0 (states are pre-settled).
      skill_mode: success = the skill chain (True) or the task goals (False); None takes `config.skill_mode`.
      batch_size: how many environments are stepped together; only MJX's Warp implementation (picked by MJX on
        a CUDA GPU with MJX_GPU_DEFAULT_WARP=true) uses it, to size the contact buffer all of them share. Under
        Warp, build batched states with a vmapped `reset` (not by indexing another batch's state).
    """

    def __init__(self, object_xml: str | Path, episodes, config: EnvConfig = EnvConfig(backend="mjx"),
                 skill_mode: bool | None = None, batch_size: int = 1):
        episodes = list(episodes)
        if not episodes:
            raise TaskError("BraxPartInstructEnv needs at least one episode, got an empty list")
        if config.backend != "mjx":
            raise SceneError(f"BraxPartInstructEnv steps MJX; EnvConfig.backend must be 'mjx', got "
                             f"'{config.backend}'")
        if config.object_noise != 0:
            raise SceneError(f"BraxPartInstructEnv starts from pre-settled states, so EnvConfig.object_noise must be "
                             f"0, got {config.object_noise}")
        object_xml = Path(object_xml)
        obj_id = object_xml.parent.name
        for e in episodes:
            if e.obj_id != obj_id:
                raise TaskError(f"episode {e.ep_id} is for object '{e.obj_id}' ({e.obj_class}), but this "
                                f"environment's object is '{obj_id}' ({object_xml})")
        poses = np.array([e.obj_pose for e in episodes], dtype=float)
        if poses.ndim != 2 or poses.shape[1] != 7:
            raise TaskError(f"obj_pose must be [qx, qy, qz, qw, x, y, z]; got shape {poses.shape[1:]}")

        self.config = config
        self.skill_mode = config.skill_mode if skill_mode is None else bool(skill_mode)
        self.episodes = episodes
        self.episode_length = max(step_limit(e.split) for e in episodes)
        """The longest step limit among the episodes (250, or 400 with test4): EpisodeWrapper's episode_length."""
        self.scene = build_scene(replace(config.scene, object_xml=str(object_xml)))
        self.geometry, self.part_names = load_parts(self.scene)
        self.kinematics = jax_ik.ArmKinematics.from_scene(self.scene)
        compiled = progress.compile_episodes([(e.task_type, list(e.chain)) for e in episodes], self.part_names)
        self._compiled = jax.tree.map(jnp.asarray, compiled)
        self.model = put_model(self.scene.model)
        self._fresh = fresh_data(self.scene.model, self.model, batch_size)
        self._indices = scene_indices(self.scene)
        self._initial = _settle(self.scene, poses, config.num_threads)

    # --- brax.envs.base.Env ------------------------------------------------------------------------------------

    @property
    def observation_size(self) -> int:
        return OBSERVATION_SIZE

    @property
    def action_size(self) -> int:
        return self.config.action_size

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def dt(self) -> float:
        """Seconds per environment step (0.05: the original's 20 Hz)."""
        return self.scene.config.control_dt

    def reset(self, rng: jax.Array) -> State:
        """Start one of the episodes (drawn uniformly from `rng`) from its settled state."""
        episode = jax.random.randint(rng, (), 0, len(self.episodes))
        start = jax.tree.map(lambda x: x[episode], self._initial)
        data = self._fresh.replace(time=start["time"], qpos=start["qpos"], qvel=start["qvel"], act=start["act"],
                            qacc_warmstart=start["qacc_warmstart"],
                            ctrl=jnp.asarray(panda.HOME_CTRL, self._fresh.ctrl.dtype))
        data = mjx.forward(self.model, data)
        scene = extract_state(self.model, data, self._indices)
        compiled = jax.tree.map(lambda x: x[episode][None], self._compiled)
        task = _unbatch(progress.initial_task_state(_batch(scene), self.geometry, compiled))
        pipeline = PipelineState(data=data, scene=scene, task=task, joint_targets=scene.arm_qpos,
                                 episode=episode.astype(jnp.int32), steps=jnp.zeros((), jnp.int32))
        return self._state(pipeline, {}, {})

    def step(self, state: State, action: jax.Array) -> State:
        """One control step of one environment with a (7,) Euler or (8,) quaternion action."""
        action = jnp.asarray(action, jnp.float32)
        if action.shape != (self.action_size,):
            raise TaskError(f"action must have shape ({self.action_size},) for rotation='{self.config.rotation}', "
                            f"got {tuple(action.shape)} (one environment; wrap the env with VmapWrapper for "
                            f"batches)")
        previous = state.pipeline_state
        ctrl = joint_targets(self.kinematics, self.config.ik, previous.joint_targets[None], action[None])[0]
        data = previous.data.replace(ctrl=ctrl.astype(previous.data.ctrl.dtype))
        data = jax.lax.fori_loop(0, self.scene.config.substeps, lambda _, d: mjx.step(self.model, d), data)
        scene = extract_state(self.model, data, self._indices)
        task = _unbatch(progress.update(_batch(previous.task), _batch(scene), self.geometry,
                                        skill_mode=self.skill_mode))
        pipeline = PipelineState(data=data, scene=scene, task=task,
                                 joint_targets=ctrl[:panda.NUM_ARM_JOINTS].astype(previous.joint_targets.dtype),
                                 episode=previous.episode, steps=previous.steps + 1)
        return self._state(pipeline, state.metrics, state.info)

    # --- helpers -----------------------------------------------------------------------------------------------

    def instructions(self, state: State) -> str | list[str]:
        """The instruction each environment's policy sees now (a list for a batched state, else one string)."""
        pipeline = state.pipeline_state
        episode, skill = np.asarray(pipeline.episode), np.asarray(pipeline.task.skill_index)
        out = []
        for e, s in zip(episode.reshape(-1), skill.reshape(-1)):
            ep = self.episodes[int(e)]
            out.append(ep.skill_instructions[min(int(s), len(ep.chain) - 1)] if self.skill_mode
                       else ep.task_instruction)
        return out if episode.ndim else out[0]

    def _state(self, pipeline: PipelineState, metrics: dict, info: dict) -> State:
        """The State of `pipeline`; keys that wrappers added to `metrics` and `info` are kept (their scans need
        the same tree after a step; EvalWrapper, for one, adds metrics['reward'])."""
        task = pipeline.task
        success = task.success.astype(jnp.float32)
        metrics = {**metrics, "success": success, "completion": task.completion.astype(jnp.float32),
                   "skill_index": task.skill_index.astype(jnp.float32), "phase": task.phase.astype(jnp.float32)}
        metrics |= {f"goal_{g}": task.goals_met[g].astype(jnp.float32) for g in range(progress.MAX_GOALS)}
        info = {**info, "episode": pipeline.episode, "joint_targets": pipeline.joint_targets,
                "env_steps": pipeline.steps}
        return State(pipeline_state=pipeline, obs=_flat_observation(pipeline.scene, task), reward=success,
                     done=success, metrics=metrics, info=info)


def _flat_observation(scene: SceneState, task: progress.TaskState) -> jnp.ndarray:
    """The OBS_LAYOUT vector of one environment, from env.observe's blocks."""
    blocks = _unbatch(observe(_batch(scene), _batch(task)))
    skill = jnp.clip(task.skill_index, 0, jnp.maximum(task.num_skills, 1) - 1)
    return jnp.concatenate([blocks["tcp_pose"], blocks["joint_states"], blocks["gripper_state"],
                            jax.nn.one_hot(skill, progress.MAX_SKILLS, dtype=jnp.float32)])


def _settle(scene, poses: np.ndarray, num_threads: int | None) -> dict[str, jnp.ndarray]:
    """Every episode's physics state after the reset settle, from the C backend (as PartInstructEnv's reset)."""
    xy = poses[:, 4:6]
    quat = np.concatenate([poses[:, 3:4], poses[:, :3]], axis=1)  # [qx, qy, qz, qw] -> MuJoCo's (w, x, y, z)
    with MujocoBackend(scene, len(poses), num_threads) as backend:
        backend.reset(xy, quat)
        fields = ("time", "qpos", "qvel", "act", "qacc_warmstart")
        return {f: jnp.asarray(np.stack([np.array(getattr(d, f)) for d in backend.datas])) for f in fields}


def _batch(tree):
    return jax.tree.map(lambda x: jnp.asarray(x)[None], tree)


def _unbatch(tree):
    return jax.tree.map(lambda x: x[0], tree)
