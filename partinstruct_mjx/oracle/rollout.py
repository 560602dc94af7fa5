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
from partinstruct_mjx.oracle import machine

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
    actions do not depend on its batch."""

    def __init__(self):
        self.state: machine.OracleState | None = None

    def reset(self, env: PartInstructEnv, state, key: jax.Array) -> None:
        keys = jnp.stack([jax.random.fold_in(key, e.ep_id if e.seed is None else e.seed % 2**31)
                          for e in env.episodes])
        self.state = machine.init(machine.compile_chains(env.episodes, env.part_names), state.data, env.geometry, keys)

    def act(self, env: PartInstructEnv, state, instructions=None, key=None) -> jnp.ndarray:
        """(B, 7) Euler actions for this step (plans first where a scene needs a grasp or touch pose)."""
        if self.state is None:
            raise TaskError("OraclePolicy.act was called before reset")
        if bool(np.asarray(self.state.needs_plan).any()):
            self.state = _plan(self.state, state.data.for_jit(), env.geometry, env.kinematics,
                               state.info["joint_targets"])
        self.state, action = _act(self.state, state.data.for_jit(), state.task, env.geometry, env.config.skill_mode)
        return action


def run_oracle(env: PartInstructEnv, episodes: list, key: jax.Array, record: bool = True) -> OracleRollout:
    """Reset `env` to `episodes`, let the oracle act until every scene's episode has ended, return the recording.

    `success` is each scene's task success at the step its episode ended. The oracle's random draws come from
    `key` folded with each episode's seed, so a scene's demo does not depend on the batch it runs in.
    """
    state = env.reset(key, episodes)
    initial_state = env.backend.get_physics_state() if hasattr(env.backend, "get_physics_state") else None
    policy = OraclePolicy()
    policy.reset(env, state, key)
    surface = point_renderer.surface_points(env.scene, env.geometry) if record else None
    batch = env.batch_size
    limit = int(np.max(np.asarray(state.info["step_limit"])))
    ended = np.zeros(batch, bool)
    success = np.zeros(batch, bool)
    length = np.zeros(batch, np.int32)
    done_for = np.zeros(batch, np.int32)
    frames: list[dict] = []
    for _ in range(limit):
        if record:
            frames.append({"obs": {k: np.asarray(v) for k, v in state.obs.items() if k != "instruction_index"},
                           "object_pose": np.asarray(original_pose(state.data.object_quat, state.data.object_pos)),
                           "body_pos": np.asarray(state.data.body_pos, np.float32),
                           "body_quat": np.asarray(state.data.body_quat, np.float32),
                           "target_mask": np.asarray(_target_masks(policy.state, surface, env.geometry)),
                           "skill": _chain_index(policy.state)})
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
        ended |= now
        if ended.all():
            break
    return OracleRollout(
        success=success, length=length, failed_skill=np.asarray(policy.state.failed_skill),
        actions=_stack(frames, "action"), skill_index=_stack(frames, "skill"),
        obs={k: np.stack([f["obs"][k] for f in frames], 1) for k in (frames[0]["obs"] if frames else {})}
        | ({"object_pose": _stack(frames, "object_pose")} if frames else {}),
        body_pos=_stack(frames, "body_pos"), body_quat=_stack(frames, "body_quat"),
        target_mask=_stack(frames, "target_mask"), initial_state=initial_state)


def _chain_index(oracle: machine.OracleState) -> np.ndarray:
    """(B,) the skill being executed; the chain's last skill once the oracle is DONE (waiting for the env)."""
    skill = np.asarray(oracle.skill)
    return np.where(skill == machine.DONE, np.asarray(oracle.num_skills) - 1, skill)


def _stack(frames: list[dict], name: str) -> np.ndarray:
    return np.stack([f[name] for f in frames], 1) if frames else np.zeros((0,))

