"""Run the oracle on episodes in a PartInstructEnv and record what a demonstration needs.

Demos use an env in task mode (the original generated its demos that way, spec 8.1): the oracle sequences the
skills itself. In skill mode (evaluation) it follows the env's skill chain, so each skill is judged as the env
judges it. A scene's episode ends at task success, at the env's step limit, when the oracle fails a skill (and has
no try left, backtrack.py), or when the oracle has executed the whole chain; the scene then takes the next episode
(`PartInstructEnv.reset_rows`), so the batch stays full however long single episodes take. Per step the recording
keeps the action, the proprioception, the skill being executed and the compact state point clouds are rendered
from later (body poses and the target-part mask).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.env import PartInstructEnv, original_pose
from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.obs import point_renderer
from partinstruct_mjx.oracle import backtrack, machine
from partinstruct_mjx.sim.state import select_rows
from partinstruct_mjx.tasks import progress

DONE_GRACE = 10
"""Steps a scene keeps stepping (the oracle holding its last command) after the oracle finished its chain."""

_plan = jax.jit(machine.plan)
_init = jax.jit(machine.init)
PLAN_ALONE = 4
"""Up to this many scenes asking for a plan in one step are planned one at a time: the planner's cost grows with
the scenes it is given, and a batch-wide call plans every scene (a streamed batch's scenes start their skills at
different steps, so most steps that plan need it for one scene). JAX on a CPU plans every scene alone: the vmapped
planner took 1.75 s for 16 scenes there, against 31 ms for one."""
_act = jax.jit(machine.act, static_argnames="follow_env")


@dataclass
class OracleEpisode:
    """What the oracle did in one episode. Arrays are (T, ...) over its `length` steps (empty without recording)."""

    index: int
    """The episode's position in the list given to `run_oracle`."""
    success: bool
    length: int
    failed_skill: int
    """Index of the chain skill that failed, -1 if none (a task that ran out of steps has -1 too); for an episode no
    attempt solved, that of the attempt that got furthest along its chain."""
    segment_tries: np.ndarray
    """(S,) the try that stood for each grasp or touch segment (0 = the first; backtrack.py); for an episode no
    attempt solved, the tries of its furthest attempt (which `OraclePolicy`'s look-ahead replays)."""
    simulated_steps: int
    """Steps its scene was simulated for it, the undone tries included."""
    unstable: bool
    """Its last attempt ended because the simulation diverged (the env's `info["unstable"]`)."""
    initial_state: np.ndarray | None
    """MuJoCo physics state after its reset (mujoco backend), for exact replay."""
    actions: np.ndarray
    skill_index: np.ndarray
    obs: dict[str, np.ndarray]
    body_pos: np.ndarray
    body_quat: np.ndarray
    target_mask: np.ndarray


@jax.jit
def _recorded(oracle: machine.OracleState, object_quat, object_pos, surface, geometry):
    """What a step records besides the env's outputs (one dispatch): the object poses in the original's layout and
    the target-part masks of the surface points."""
    index = jnp.clip(oracle.skill, 0, oracle.kind.shape[1] - 1)
    part = jnp.take_along_axis(oracle.part, index[:, None], axis=1)[:, 0]
    part = jnp.where(oracle.skill == machine.DONE, -1, part)
    masks = jax.vmap(point_renderer.target_mask, in_axes=(None, None, 0, 0))(surface, geometry, oracle.masks, part)
    return original_pose(object_quat, object_pos), masks


class OraclePolicy:
    """The oracle as a policy (the evaluator's `reset`/`act` interface): it reads privileged information (the
    episodes' chains, part geometry, the physics state) and ignores instructions. In a skill-mode env it follows the
    env's skill chain. Its random draws come from the reset key folded with each episode's seed, so an episode's
    actions do not depend on the other episodes of its batch.

    With `lookahead_tries` > 1 it plans each batch first in a private copy of the env (same object, batch and
    config, reset with the same key): `run_oracle` there backtracks failed grasps and touches (backtrack.py), and
    the policy then makes, at each segment's start, the random draws of the try that stood. The env itself is never
    rewound; on the deterministic C MuJoCo backend it repeats the copy's steps exactly. The look-ahead does not start
    an episode over (`run_oracle`'s restarts): the evaluation's figures in docs/evaluation.md are measured without."""

    def __init__(self, lookahead_tries: int = 1):
        self.lookahead_tries = lookahead_tries
        self.state: machine.OracleState | None = None
        self._choices: np.ndarray | None = None
        self._segment: np.ndarray | None = None
        self._copy: PartInstructEnv | None = None

    def reset(self, env: PartInstructEnv, state, key: jax.Array) -> None:
        self.state = _initial_machine(env, state, key)
        if self.lookahead_tries > 1:
            self._choices = np.zeros((env.batch_size, progress.MAX_SKILLS), np.int32)
            for episode in run_oracle(self._private_copy(env), env.episodes, key, record=False,
                                      tries=self.lookahead_tries, restarts=0):
                self._choices[episode.index] = episode.segment_tries
            self._segment = np.zeros(env.batch_size, np.int32)
            self.state = backtrack.with_try(self.state, self._choices[:, 0], self.lookahead_tries)

    def fork(self) -> OraclePolicy:
        """An oracle for another worker thread (its own machine state and look-ahead copy)."""
        return OraclePolicy(self.lookahead_tries)

    def reset_rows(self, env: PartInstructEnv, state, key: jax.Array, rows: np.ndarray) -> None:
        """New episodes in the scenes of `rows` (after `env.reset_rows`); without look-ahead only."""
        if self._choices is not None:
            raise TaskError("reset_rows is not available with lookahead_tries > 1")
        self.state = select_rows(rows, _initial_machine(env, state, key), self.state)

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
        data, joints = state.data.for_jit(), state.info["joint_targets"]
        need = np.flatnonzero(np.asarray(self.state.needs_plan))
        if len(need) > PLAN_ALONE and jax.default_backend() != "cpu":
            self.state = _plan(self.state, data, env.geometry, env.kinematics, joints)
        else:
            for b in need:
                self.state = _plan_scene(self.state, data, env.geometry, env.kinematics, joints, b)
        before = self.state
        self.state, action = _act(self.state, data, state.task, env.geometry, env.config.skill_mode)
        if self._choices is not None:
            starts = backtrack.segment_starts(before, self.state)
            if starts.any():
                self._segment = np.minimum(self._segment + starts, self._choices.shape[1] - 1)
                tries = np.where(starts, self._choices[np.arange(len(starts)), self._segment], 0)
                self.state = backtrack.with_try(self.state, tries, self.lookahead_tries)
        return action


def _plan_scene(oracle: machine.OracleState, data, geometry, kinematics, joints, row) -> machine.OracleState:
    """`machine.plan` for the scene in `row` alone (a batch of one), written back into the batch's machine state.
    The planner is traced and compiled once for batches of one, whatever the batch size: traced inside one jitted
    function with the row's slicing, it took 6 s to trace and 3 s to compile (or load) per batch size, and an
    evaluation's batches come in several sizes."""
    one_oracle, one_data, one_joints = _take_row((oracle, data, joints), row)
    return _put_row(oracle, _plan(one_oracle, one_data, geometry, kinematics, one_joints), row)


@jax.jit
def _take_row(tree, row):
    """The batch of one of `tree`'s arrays at batch row `row`."""
    return jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, row, 1), tree)


@jax.jit
def _put_row(whole, part, row):
    """`whole` with its batch row `row` replaced by the batch of one `part`."""
    return jax.tree.map(lambda w, p: jax.lax.dynamic_update_slice_in_dim(w, p, row, 0), whole, part)


def _initial_machine(env: PartInstructEnv, state, key: jax.Array) -> machine.OracleState:
    """Machine state at the start of every scene's episode; keys from `key` folded with each episode's seed."""
    seeds = np.array([e.ep_id if e.seed is None else e.seed % 2**31 for e in env.episodes], np.uint32)
    keys = jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, seeds)
    return _init(machine.compile_chains(env.episodes, env.part_names), state.data, env.geometry, keys)


def run_oracle(env: PartInstructEnv, episodes: list, key: jax.Array, record: bool = True,
               tries: int = backtrack.SEGMENT_TRIES, restarts: int = backtrack.RESTARTS) -> Iterator[OracleEpisode]:
    """Run `episodes` (any number) through `env`'s scenes and yield each one's `OracleEpisode` as it ends.

    The first B episodes start at reset (fewer fill the batch by repeating, and the repeats are not reported); a
    scene whose episode ended takes the next one. `success` is the task success at the step the episode ended. The
    oracle's random draws come from `key` folded with each episode's seed, so an episode's outcome depends neither on
    its scene nor on the episodes beside it; with JAX on a CPU batches of 1 to 4 scenes act alike (jax_ik.MIN_BATCH;
    tests/test_oracle.py), while other batch sizes may round the IK 1 ulp apart on some CPUs. A failed grasp or
    touch and what follows it is tried up to `tries` times from the state before it, and an episode that every try
    failed starts over up to `restarts` times (backtrack.py); the recording holds the episode's steps along the tries
    that stood.
    """
    if not episodes:
        return
    batch = env.batch_size
    pending = list(enumerate(episodes))
    first = pending[:batch]
    owner = np.array([i for i, _ in first] + [-1] * (batch - len(first)))
    state = env.reset(key, [first[b % len(first)][1] for b in range(batch)])
    get_physics = getattr(env.backend, "get_physics_state", None)
    initial = get_physics() if get_physics else None
    del pending[:batch]
    policy = OraclePolicy()
    policy.reset(env, state, key)
    search = backtrack.Backtracker(env, state, policy.state, tries, restarts)
    surface = point_renderer.surface_points(env.scene, env.geometry) if record else None
    length = np.zeros(batch, np.int32)
    simulated = np.zeros(batch, np.int32)
    done_for = np.zeros(batch, np.int32)
    # The batch's recorded steps by number, and each scene's step numbers along the tries that stood.
    frames: dict[int, dict] = {}
    steps: list[list[int]] = [[] for _ in range(batch)]
    first_frame = np.zeros(batch, np.int64)
    for number in itertools.count():
        active = owner >= 0
        if not active.any():
            return
        if record:
            frame = {"obs": {k: np.asarray(v) for k, v in state.obs.items() if k != "instruction_index"},
                     "body_pos": np.asarray(state.data.body_pos, np.float32),
                     "body_quat": np.asarray(state.data.body_quat, np.float32),
                     "skill": _chain_index(policy.state)}
            frame["object_pose"], frame["target_mask"] = map(np.asarray, _recorded(
                policy.state, state.data.object_quat, state.data.object_pos, surface, env.geometry))
        before = policy.state
        action = policy.act(env, state)
        if record:
            frame["action"] = np.asarray(action)
            frames[number] = frame
            for b in np.flatnonzero(active):
                steps[b].append(number)
        state = env.step(state, action, active)
        length += active
        simulated += active
        oracle = policy.state
        # The env judges the last skill one step after the oracle did: it gets DONE_GRACE steps to agree.
        done_for = np.where(np.asarray(oracle.skill) == machine.DONE, done_for + 1, 0)
        now = active & (np.asarray(state.done) | np.asarray(oracle.failed) | (done_for > DONE_GRACE))
        success = np.asarray(state.task.success)
        retried, state, policy.state = search.retry(now & ~success, state, oracle)
        for b in np.flatnonzero(retried):
            del steps[b][search.saved_steps[b]:]
        length = np.where(retried, search.saved_steps, length)
        done_for = np.where(retried, 0, done_for)
        search.save(backtrack.segment_starts(before, policy.state) & active & ~now, state, policy.state, length)
        ended = now & ~retried
        unstable = np.asarray(state.info["unstable"]) if ended.any() else None  # read back only when needed
        for b in np.flatnonzero(ended):
            # An episode no attempt solved reports its furthest attempt: the look-ahead replays that one.
            failed_skill, tries = ((int(policy.state.failed_skill[b]), search.chosen[b]) if success[b] else
                                   (int(search.furthest_failed_skill[b]), search.furthest_chosen[b]))
            yield _episode(int(owner[b]), bool(success[b]), int(length[b]), failed_skill, tries.copy(),
                           int(simulated[b]), bool(unstable[b]), None if initial is None else initial[b].copy(),
                           [frames[n] for n in steps[b]], b)
        owner[ended] = -1
        free = np.flatnonzero(owner < 0)[:len(pending)]
        if len(free):
            rows = np.isin(np.arange(batch), free)
            state = env.reset_rows(state, key, rows, [e for _, e in pending[:len(free)]])
            owner[free] = [i for i, _ in pending[:len(free)]]
            del pending[:len(free)]
            policy.reset_rows(env, state, key, rows)
            search.start(rows, state, policy.state)
            if get_physics:
                initial[free] = get_physics()[free]
            length[free] = simulated[free] = done_for[free] = 0
            first_frame[free] = number + 1
            for b in free:
                steps[b] = []
        oldest = first_frame[owner >= 0].min(initial=number + 1)
        for old in [n for n in frames if n < oldest]:
            del frames[old]


def _episode(index: int, success: bool, length: int, failed_skill: int, segment_tries: np.ndarray,
             simulated: int, unstable: bool, initial_state, frames: list[dict], row: int) -> OracleEpisode:
    """An OracleEpisode from the batch frames of its steps (as run_oracle records them) and its scene's row."""
    stacked = jax.tree.map(lambda *xs: np.stack([x[row] for x in xs]), *frames) if frames else None
    empty = np.zeros((0,))
    return OracleEpisode(
        index=index, success=success, length=length, failed_skill=failed_skill, segment_tries=segment_tries,
        simulated_steps=simulated, unstable=unstable, initial_state=initial_state,
        actions=stacked["action"] if stacked else empty, skill_index=stacked["skill"] if stacked else empty,
        obs=(stacked["obs"] | {"object_pose": stacked["object_pose"]}) if stacked else {},
        body_pos=stacked["body_pos"] if stacked else empty, body_quat=stacked["body_quat"] if stacked else empty,
        target_mask=stacked["target_mask"] if stacked else empty)


def _chain_index(oracle: machine.OracleState) -> np.ndarray:
    """(B,) the skill being executed; the chain's last skill once the oracle is DONE (waiting for the env)."""
    skill = np.asarray(oracle.skill)
    return np.where(skill == machine.DONE, np.asarray(oracle.num_skills) - 1, skill)
