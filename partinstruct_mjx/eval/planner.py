"""The high-level planner interface of bi-level evaluation (spec 10) and the ground-truth planner.

A planner turns the task (and whatever it observes) into the instruction each scene's low-level policy follows.
The runner consults it at step 0 of every batch of new episodes and then every `planner_every` steps, and hands
its latest answer to `Policy.act`; a VLM/LLM planner plugs in by implementing `instructions`.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from partinstruct_mjx.eval.config import PLANNERS, EvalError
from partinstruct_mjx.eval.skills import SkillProgress


@runtime_checkable
class Planner(Protocol):
    """Chooses the instruction each scene's low-level policy follows. Optional, as for policies: `fork() -> Planner`,
    a planner for another worker thread."""

    def instructions(self, env, state, step: int) -> list[str]:
        """One instruction per scene of the batch; `step` is the env step about to be taken (0: new episodes, whose
        task instructions are `[e.task_instruction for e in env.episodes]`)."""


class OraclePlanner:
    """Ground-truth plan: the instruction of the skill each scene's chain has reached.

    In skill mode that is the env's own skill progress; in task mode the skills are judged the same way on the states
    the planner is consulted with, so with `planner_every` > 1 a finished skill is noticed at the next consultation.
    """

    def __init__(self):
        self._progress: SkillProgress | None = None

    def fork(self) -> OraclePlanner:
        """A planner for another worker thread (its own skill progress)."""
        return OraclePlanner()

    def instructions(self, env, state, step: int) -> list[str]:
        if step == 0 or self._progress is None or self._progress.env is not env:
            self._progress = SkillProgress(env)
            self._progress.reset(state)
        else:
            self._progress.update(state)
        index = self._progress.index(state)
        return [e.skill_instructions[min(int(i), len(e.chain) - 1)] for e, i in zip(env.episodes, index)]


def make_planner(name: str | None) -> Planner | None:
    """The planner a CLI name stands for (None: none)."""
    if name is None:
        return None
    if name == "oracle":
        return OraclePlanner()
    raise EvalError(f"unknown planner '{name}'; expected one of {', '.join(PLANNERS)}")
