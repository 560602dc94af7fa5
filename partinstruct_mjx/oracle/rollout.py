"""Run the oracle on a batch of episodes in a PartInstructEnv and record what a demonstration needs.

Demos use an env in task mode (the original generated its demos that way, spec 8.1): the oracle sequences the
skills itself. In skill mode (evaluation) it follows the env's skill chain, so each skill is judged as the env
judges it. A scene's episode ends at task success, at the env's step limit, when the oracle fails a skill, or when
the oracle has executed the whole chain. Per step the recording keeps the action, the proprioception, the skill
being executed and the compact state point clouds are rendered from later (body poses and the target-part mask).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.env import PartInstructEnv, original_pose
from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.obs import point_renderer
from partinstruct_mjx.oracle import backtrack, machine

DONE_GRACE = 10
"""Steps a scene keeps stepping (the oracle holding its last command) after the oracle finished its chain."""

_plan = jax.jit(machine.plan)
_act = jax.jit(machine.act, static_argnames="follow_env")


@dataclass
class OracleRollout:
    """What a batch of oracle episodes did. Arrays are (B, T, ...) over the longest episode; `length` cuts each."""

    success: np.ndarray
    length: np.ndarray
    failed_skill: np.ndarray
    """(B,) index of the chain skill that failed, -1 if none (a task that ran out of steps has -1 too)."""
    actions: np.ndarray
    skill_index: np.ndarray
    obs: dict[str, np.ndarray]
    body_pos: np.ndarray
    body_quat: np.ndarray
    target_mask: np.ndarray
    initial_state: np.ndarray | None
    segment_tries: np.ndarray
    """(B, S) the try that stood for each grasp or touch segment (0 = the first; backtrack.py)."""
    simulated_steps: int
    """Steps the batch was simulated, the undone tries included."""


@jax.jit
def _target_masks(oracle: machine.OracleState, surface, geometry):
    index = jnp.clip(oracle.skill, 0, oracle.kind.shape[1] - 1)
    part = jnp.take_along_axis(oracle.part, index[:, None], axis=1)[:, 0]
    part = jnp.where(oracle.skill == machine.DONE, -1, part)
    return jax.vmap(point_renderer.target_mask, in_axes=(None, None, 0, 0))(surface, geometry, oracle.masks, part)


class OraclePolicy:
    """The oracle as a policy (the evaluator's `reset`/`act` interface): it reads privileged information (the
    episodes' chains, part geometry, the physics state) and ignores instructions. In a skill-mode env it follows the
    env's skill chain. Its random draws come from the reset key folded with each episode's seed, so an episode's
    actions do not depend on its batch.

    With `lookahead_tries` > 1 it plans each batch first in a private copy of the env (same object, batch and
    config, reset with the same key): `run_oracle` there backtracks failed grasps and touches (backtrack.py), and
    the policy then makes, at each segment's start, the random draws of the try that stood. The env itself is never
    rewound; on the deterministic C MuJoCo backend it repeats the copy's steps exactly."""

    def __init__(self, lookahead_tries: int = 1):
        self.lookahead_tries = lookahead_tries
        self.state: machine.OracleState | None = None
        self._choices: np.ndarray | None = None
        self._segment: np.ndarray | None = None
        self._copy: PartInstructEnv | None = None

    def reset(self, env: PartInstructEnv, state, key: jax.Array) -> None:
        keys = jnp.stack([jax.random.fold_in(key, e.ep_id if e.seed is None else e.seed % 2**31)
                          for e in env.episodes])
        self.state = machine.init(machine.compile_chains(env.episodes, env.part_names), state.data, env.geometry, keys)
        if self.lookahead_tries > 1:
            self._choices = run_oracle(self._private_copy(env), env.episodes, key, record=False,
                                       tries=self.lookahead_tries).segment_tries
            self._segment = np.zeros(env.batch_size, np.int32)
            self.state = backtrack.with_try(self.state, self._choices[:, 0])

    def close(self) -> None:
        """Close the private copy of the env (lookahead only)."""
        if self._copy is not None:
            self._copy.close()
            self._copy = None

    def _private_copy(self, env: PartInstructEnv) -> PartInstructEnv:
        copy = self._copy
        if copy is None or (copy.scene.object_xml, copy.batch_size, copy.config) != (
                env.scene.object_xml, env.batch_size, env.config):
            self.close()
            self._copy = PartInstructEnv(env.scene.object_xml, env.batch_size, env.config)
        return self._copy

    def act(self, env: PartInstructEnv, state, instructions=None, key=None) -> jnp.ndarray:
        """(B, 7) Euler actions for this step (plans first where a scene needs a grasp or touch pose)."""
        if self.state is None:
            raise TaskError("OraclePolicy.act was called before reset")
        if bool(np.asarray(self.state.needs_plan).any()):
            self.state = _plan(self.state, state.data.for_jit(), env.geometry, env.kinematics,
                               state.info["joint_targets"])
        before = self.state
        self.state, action = _act(self.state, state.data.for_jit(), state.task, env.geometry, env.config.skill_mode)
        if self._choices is not None:
            starts = backtrack.segment_starts(before, self.state)
            if starts.any():
                self._segment = np.minimum(self._segment + starts, self._choices.shape[1] - 1)
                tries = np.where(starts, self._choices[np.arange(len(starts)), self._segment], 0)
                self.state = backtrack.with_try(self.state, tries)
        return action


def run_oracle(env: PartInstructEnv, episodes: list, key: jax.Array, record: bool = True,
               tries: int = backtrack.SEGMENT_TRIES) -> OracleRollout:
    """Reset `env` to `episodes`, let the oracle act until every scene's episode has ended, return the recording.

    `success` is each scene's task success at the step its episode ended. The oracle's random draws come from
    `key` folded with each episode's seed, so a scene's demo does not depend on the batch it runs in. A failed
    grasp or touch and what follows it is tried up to `tries` times from the state before it (backtrack.py); the
    recording holds each scene's steps from its start along the tries that stood.
    """
    state = env.reset(key, episodes)
    initial_state = env.backend.get_physics_state() if hasattr(env.backend, "get_physics_state") else None
    policy = OraclePolicy()
    policy.reset(env, state, key)
    search = backtrack.Backtracker(env, state, policy.state, tries)
    surface = point_renderer.surface_points(env.scene, env.geometry) if record else None
    batch = env.batch_size
    limit = int(np.max(np.asarray(state.info["step_limit"])))
    ended = np.zeros(batch, bool)
    success = np.zeros(batch, bool)
    length = np.zeros(batch, np.int32)
    done_for = np.zeros(batch, np.int32)
    frames: list[dict] = []
    # timeline[b, t]: the frame that holds step t of scene b's demonstration.
    timeline = np.zeros((batch, limit * tries), np.int32)
    for frame in range(limit * tries):
        timeline[np.arange(batch), length] = frame
        if record:
            frames.append({"obs": {k: np.asarray(v) for k, v in state.obs.items() if k != "instruction_index"},
                           "object_pose": np.asarray(original_pose(state.data.object_quat, state.data.object_pos)),
                           "body_pos": np.asarray(state.data.body_pos, np.float32),
                           "body_quat": np.asarray(state.data.body_quat, np.float32),
                           "target_mask": np.asarray(_target_masks(policy.state, surface, env.geometry)),
                           "skill": _chain_index(policy.state)})
        before = policy.state
        action = policy.act(env, state)
        if record:
            frames[-1]["action"] = np.asarray(action)
        state = env.step(state, action)
        length += ~ended
        oracle = policy.state
        # The env judges the last skill one step after the oracle did: it gets DONE_GRACE steps to agree.
        done_for = np.where(np.asarray(oracle.skill) == machine.DONE, done_for + 1, 0)
        now = np.asarray(state.done) | np.asarray(oracle.failed) | (done_for > DONE_GRACE)
        success = np.where(ended, success, np.asarray(state.task.success))
        retried, state, policy.state = search.retry(now & ~success & ~ended, state, oracle)
        length = np.where(retried, search.saved_steps, length)
        done_for = np.where(retried, 0, done_for)
        search.save(backtrack.segment_starts(before, policy.state) & ~now & ~ended, state, policy.state, length)
        ended |= now & ~retried
        if ended.all():
            break
    # Past its end a scene's recording repeats its last step (consumers cut at `length`).
    rows = np.take_along_axis(timeline, np.minimum(np.arange(length.max()), length[:, None] - 1), axis=1)
    return OracleRollout(
        success=success, length=length, failed_skill=np.asarray(policy.state.failed_skill),
        actions=_gather(frames, "action", rows), skill_index=_gather(frames, "skill", rows),
        obs={k: _gather([f["obs"] for f in frames], k, rows) for k in (frames[0]["obs"] if frames else {})}
        | ({"object_pose": _gather(frames, "object_pose", rows)} if frames else {}),
        body_pos=_gather(frames, "body_pos", rows), body_quat=_gather(frames, "body_quat", rows),
        target_mask=_gather(frames, "target_mask", rows), initial_state=initial_state,
        segment_tries=search.chosen, simulated_steps=frame + 1)


def _chain_index(oracle: machine.OracleState) -> np.ndarray:
    """(B,) the skill being executed; the chain's last skill once the oracle is DONE (waiting for the env)."""
    skill = np.asarray(oracle.skill)
    return np.where(skill == machine.DONE, np.asarray(oracle.num_skills) - 1, skill)


def _gather(frames: list[dict], name: str, timeline: np.ndarray) -> np.ndarray:
    """(B, T, ...) scene b's `name` at the frames `timeline[b]` (B, T)."""
    if not frames:
        return np.zeros((0,))
    stacked = np.stack([f[name] for f in frames], 1)
    return stacked[np.arange(stacked.shape[0])[:, None], timeline]

