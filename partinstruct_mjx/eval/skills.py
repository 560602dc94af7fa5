"""Which skill of its ground-truth chain each scene has reached, judged the way skill mode judges it (spec 7)."""

from __future__ import annotations

import jax
import numpy as np

from partinstruct_mjx.tasks import progress

_skill_update = jax.jit(progress.update, static_argnames="skill_mode")


class SkillProgress:
    """Skill-chain progress of an env's batch, in either env mode.

    In skill mode it is the env's own progress. In task mode the env checks the task's goals instead, so a copy of
    the env's task state is advanced with the skill-mode update on every state `update` is shown (p0 and the spatial
    parts refreshed when a skill completes, as skill mode does).
    """

    def __init__(self, env):
        self.env = env
        self._task = None

    def reset(self, state) -> None:
        """Start tracking the episodes `state` was just reset to."""
        self._task = None if self.env.config.skill_mode else state.task

    def update(self, state) -> None:
        """Judge the current skill on `state` (a no-op in skill mode, where the env does it every step)."""
        if self._task is not None:
            self._task = _skill_update(self._task, state.data, self.env.geometry, skill_mode=True)

    def index(self, state) -> np.ndarray:
        """(B,) index of the skill each scene is at; the chain length once every skill is complete."""
        task = state.task if self._task is None else self._task
        return np.asarray(task.skill_index)
