"""Backtracking for demo synthesis: a failed contact is tried again from the simulator state saved before it.

A segment is a grasp or touch skill and the skills after it up to the next grasp or touch: everything the oracle
does with one contact. When a segment fails (the oracle fails a skill, or the episode ends without success), the
scene goes back to the state saved when the segment started (physics, environment and machine state) and the oracle
plans again with other random draws (another grasp or touch sample, whose best candidates it passes over: they are
most often the one that failed), up to `tries` times in all. A segment that has spent its tries sends the scene
back to the previous segment's next try (at most RETREATS times an episode): a push can leave the object where no
grasp after it holds. An episode whose tries and retreats are all spent starts over from its reset state (at most
RESTARTS times), with fresh draws for every segment. The demonstration keeps only the steps of the tries that stand,
so it is one real trajectory from the episode's start: its actions, replayed from the initial state, reproduce it. A
try that finds no candidate at all fails like any other.
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

SEGMENT_TRIES = 10
"""Tries per segment in demo synthesis (1 = no backtracking)."""
TRY_SKIP = 2
"""Try k of a segment passes over the k * TRY_SKIP best reachable candidates of its fresh sample (each grasp comes
with both closing directions), so it does not take the grasp that failed again."""
RETREATS = 2
"""Times an episode may go back to its previous segment, to that segment's next try, once a later segment has
spent all its tries: what the earlier contact left (where a push ended, the arm's joints after it) can make every
try of the next one fail. The later segment then starts again with all its tries."""
RESTARTS = 2
"""Times an episode whose tries and retreats are all spent starts over from its reset state, its first segment's
try numbers going on from `tries` (fresh draws, none passed over) and every later segment's tries afresh. Where the
outcome hangs on its draws, a whole new set of them often succeeds: of the 49 episodes of the forty-fourth
session's 880-episode table that every try had failed, 12 succeed with two restarts (docs/oracle.md)."""


class Backtracker:
    """Per scene: the state saved at the start of each segment of its episode so far, and the try that stands for
    each."""

    def __init__(self, env: PartInstructEnv, state: State, oracle: machine.OracleState, tries: int,
                 restarts: int = RESTARTS):
        self.env, self.tries, self.restarts = env, tries, restarts if tries > 1 else 0
        batch = env.batch_size
        self._saved = [self._captured(state, oracle)]
        """Per segment number: (physics, env state, machine state) of the batch, valid in the rows that saved it."""
        self._saved_steps = np.zeros((batch, progress.MAX_SKILLS), np.int32)
        self.segment = np.zeros(batch, np.int32)
        self.chosen = np.zeros((batch, progress.MAX_SKILLS), np.int32)
        """(B, S) the try (0 = the first) that stands for each segment so far (`OraclePolicy`'s look-ahead makes
        the same choices in the evaluated env); the first segment's goes on counting over the episode's restarts."""
        self.retreats = np.zeros(batch, np.int32)
        self.started_over = np.zeros(batch, np.int32)
        self.furthest = np.full(batch, -1, np.int32)
        """(B,) how far the episode's furthest failed attempt so far got (the chain skill it stopped at)."""
        self.furthest_chosen = np.zeros_like(self.chosen)
        self.furthest_failed_skill = np.full(batch, -1, np.int32)
        """That attempt's tries per segment and failed skill: what an episode no attempt solved reports (the last
        attempt of a segment with its best candidates passed over often fails before the first did)."""

    @property
    def saved_steps(self) -> np.ndarray:
        """(B,) steps of each scene's demonstration before its current segment."""
        return self._saved_steps[np.arange(len(self.segment)), self.segment]

    def save(self, rows: np.ndarray, state: State, oracle: machine.OracleState, steps: np.ndarray) -> None:
        """Scenes where `rows` holds start a segment now (`steps` into their demonstration)."""
        if rows.any():
            self._begin(rows, np.where(rows, self.segment + 1, self.segment), state, oracle, steps)

    def start(self, rows: np.ndarray, state: State, oracle: machine.OracleState) -> None:
        """Scenes where `rows` holds start a new episode (its first segment) now."""
        if rows.any():
            self.retreats = np.where(rows, 0, self.retreats)
            self.started_over = np.where(rows, 0, self.started_over)
            self.furthest = np.where(rows, -1, self.furthest)
            self.chosen[rows] = 0
            self._begin(rows, np.where(rows, 0, self.segment), state, oracle, np.zeros_like(self.segment))

    def retry(self, failed: np.ndarray, state: State, oracle: machine.OracleState):
        """Send the `failed` scenes that have tries left back to their segment's start, or, with its tries spent, to
        the previous segment's start (at most RETREATS times an episode), or, with those spent too, to the episode's
        start (at most `restarts` times). Returns the rows sent back, the new env state and machine state (the
        machine's random key folded with the try's number)."""
        self._remember_furthest(failed, oracle)
        scenes, segment = np.arange(len(failed)), self.segment
        tried = self.chosen % self.tries + 1
        again = failed & (tried[scenes, segment] < self.tries)
        back = (failed & ~again & (segment > 0) & (self.retreats < RETREATS)
                & (tried[scenes, np.maximum(segment - 1, 0)] < self.tries))
        anew = failed & ~again & ~back & (self.started_over < self.restarts)
        rows = again | back | anew
        if not rows.any():
            return rows, state, oracle
        self.chosen[back, segment[back]] = 0
        self.segment = segment = np.where(back, segment - 1, np.where(anew, 0, segment))
        self.retreats = np.where(anew, 0, self.retreats + back)
        self.started_over = self.started_over + anew
        self.chosen[anew] = 0
        self.chosen[anew, 0] = self.started_over[anew] * self.tries - 1
        self.chosen[rows, segment[rows]] += 1
        physics, env_state, saved_oracle = self._saved[0]
        for number in range(1, len(self._saved)):
            physics, env_state, saved_oracle = select_rows(segment == number, self._saved[number],
                                                           (physics, env_state, saved_oracle))
        data = self.env.backend.restore(physics, rows)
        state = select_rows(rows, env_state, state.replace(data=None)).replace(data=data)
        tries = self.chosen[scenes, segment]
        return rows, state, select_rows(rows, with_try(saved_oracle, tries, self.tries), oracle)

    def _remember_furthest(self, failed: np.ndarray, oracle: machine.OracleState) -> None:
        """Keep the choices of each `failed` attempt that got further along its chain than the episode's others."""
        if not failed.any():
            return
        failed_skill, skill = np.asarray(oracle.failed_skill), np.asarray(oracle.skill)
        reached = np.where(failed_skill >= 0, failed_skill,
                           np.where(skill == machine.DONE, np.asarray(oracle.num_skills), skill))
        further = failed & (reached > self.furthest)
        self.furthest = np.where(further, reached, self.furthest)
        self.furthest_chosen[further] = self.chosen[further]
        self.furthest_failed_skill = np.where(further, failed_skill, self.furthest_failed_skill)

    def _begin(self, rows, segment, state: State, oracle: machine.OracleState, steps) -> None:
        """Save the state of the `rows` scenes as the start of their segment number `segment`, with its first try."""
        self.segment = segment
        captured = self._captured(state, oracle)
        for number in np.unique(segment[rows]):
            here = rows & (segment == number)
            while len(self._saved) <= number:
                self._saved.append(captured)
            self._saved[number] = select_rows(here, captured, self._saved[number])
        self._saved_steps[rows, segment[rows]] = steps[rows]
        self.chosen[rows, segment[rows]] = 0

    def _captured(self, state: State, oracle: machine.OracleState):
        return self.env.backend.snapshot(), state.replace(data=None), oracle


def with_try(oracle: machine.OracleState, tries: np.ndarray, per_round: int) -> machine.OracleState:
    """The machine state with each scene's random key folded with its try number and its candidate skip set to
    TRY_SKIP times the try's number within its round of `per_round` tries (try 0 keeps both; a restart's first try
    has a fresh key and passes over none)."""
    folded = jax.vmap(jax.random.fold_in)(oracle.key, tries)
    rows = np.asarray(tries) > 0
    skip = jnp.where(rows, TRY_SKIP * (jnp.asarray(tries, jnp.int32) % per_round), oracle.skip)
    return oracle.replace(key=select_rows(rows, folded, oracle.key), skip=skip)


def segment_starts(before: machine.OracleState, after: machine.OracleState) -> np.ndarray:
    """(B,) scenes whose machine moved on to a grasp or touch skill in this step."""
    skill = np.asarray(after.skill)
    kind = np.take_along_axis(np.asarray(after.kind), np.maximum(skill, 0)[:, None], axis=1)[:, 0]
    return (skill != np.asarray(before.skill)) & (skill >= 0) & np.isin(kind, (GRASP, TOUCH))
