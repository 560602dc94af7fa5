"""Backtracking for demo synthesis: a failed contact is tried again from the simulator state saved before it.

A segment is a grasp or touch skill and the skills after it up to the next grasp or touch: everything the oracle
does with one contact. When a segment fails (the oracle fails a skill, or the episode ends without success), the
scene goes back to the state saved when the segment started (physics, environment and machine state) and the oracle
plans again with other random draws (another grasp or touch sample, whose best candidates it passes over: they are
most often the one that failed), up to `tries` times in all. The demonstration keeps only the steps of the try that
stands, so it is one real trajectory from the episode's start: its actions, replayed from the initial state,
reproduce it. A try that finds no candidate at all fails like any other.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.env import PartInstructEnv, State
from partinstruct_mjx.oracle import machine
from partinstruct_mjx.oracle.kinds import GRASP, TOUCH
from partinstruct_mjx.sim.state import select_rows
from partinstruct_mjx.tasks import progress

SEGMENT_TRIES = 6
"""Tries per segment in demo synthesis (1 = no backtracking)."""
TRY_SKIP = 2
"""Try k of a segment passes over the k * TRY_SKIP best reachable candidates of its fresh sample (each grasp comes
with both closing directions), so it does not take the grasp that failed again."""


class Backtracker:
    """Per scene: the state saved at the start of its current segment, and the tries spent on it."""

    def __init__(self, env: PartInstructEnv, state: State, oracle: machine.OracleState, tries: int):
        self.env, self.tries = env, tries
        batch = env.batch_size
        self._physics = env.backend.snapshot()
        self._env_state = state.replace(data=None)
        self._oracle = oracle
        self.saved_steps = np.zeros(batch, np.int32)
        """Steps of each scene's demonstration before its current segment."""
        self.spent = np.zeros(batch, np.int32)
        self.segment = np.zeros(batch, np.int32)
        self.chosen = np.zeros((batch, progress.MAX_SKILLS), np.int32)
        """(B, S) the try (0 = the first) that stands for each segment so far (`OraclePolicy`'s look-ahead makes
        the same choices in the evaluated env)."""

    def save(self, rows: np.ndarray, state: State, oracle: machine.OracleState, steps: np.ndarray) -> None:
        """Scenes where `rows` holds start a segment now (`steps` into their demonstration)."""
        if not rows.any():
            return
        self._physics = select_rows(rows, self.env.backend.snapshot(), self._physics)
        self._env_state = select_rows(rows, state.replace(data=None), self._env_state)
        self._oracle = select_rows(rows, oracle, self._oracle)
        self.saved_steps = np.where(rows, steps, self.saved_steps)
        self.spent = np.where(rows, 0, self.spent)
        self.segment = np.where(rows, self.segment + 1, self.segment)

    def start(self, rows: np.ndarray, state: State, oracle: machine.OracleState) -> None:
        """Scenes where `rows` holds start a new episode (its first segment) now."""
        self.save(rows, state, oracle, np.zeros_like(self.saved_steps))
        self.segment = np.where(rows, 0, self.segment)
        self.chosen[rows] = 0

    def retry(self, failed: np.ndarray, state: State, oracle: machine.OracleState):
        """Send the `failed` scenes that have tries left back to their segment's start. Returns the rows sent back,
        the new env state and machine state (the machine's random key folded with the try's number)."""
        rows = failed & (self.spent + 1 < self.tries)
        if not rows.any():
            return rows, state, oracle
        self.spent = np.where(rows, self.spent + 1, self.spent)
        self.chosen[rows, self.segment[rows]] = self.spent[rows]
        data = self.env.backend.restore(self._physics, rows)
        state = select_rows(rows, self._env_state, state.replace(data=None)).replace(data=data)
        return rows, state, select_rows(rows, with_try(self._oracle, self.spent), oracle)


def with_try(oracle: machine.OracleState, tries: np.ndarray) -> machine.OracleState:
    """The machine state with each scene's random key folded with its try number and its candidate skip set to
    TRY_SKIP times it (try 0 keeps both)."""
    folded = jax.vmap(jax.random.fold_in)(oracle.key, tries)
    rows = np.asarray(tries) > 0
    skip = jnp.where(rows, TRY_SKIP * jnp.asarray(tries, jnp.int32), oracle.skip)
    return oracle.replace(key=select_rows(rows, folded, oracle.key), skip=skip)


def segment_starts(before: machine.OracleState, after: machine.OracleState) -> np.ndarray:
    """(B,) scenes whose machine moved on to a grasp or touch skill in this step."""
    skill = np.asarray(after.skill)
    kind = np.take_along_axis(np.asarray(after.kind), np.maximum(skill, 0)[:, None], axis=1)[:, 0]
    return (skill != np.asarray(before.skill)) & (skill >= 0) & np.isin(kind, (GRASP, TOUCH))
