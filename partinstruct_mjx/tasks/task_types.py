"""The 16 task types (spec 6.1): skill chains built from slots, and task-mode goals per phase.

Slots: P1 is the part first interacted with (grasped or touched), P2 the part that is rotated, P3 the part grasped
after a push-and-release; D1, D2 are directions. Goals follow the paper's intent where the original's checks are
buggy (spec 12 #4-#8; listed in docs/differences.md): the unit distance is always applied, type 7 uses 0.05 m,
types 1/2 include ON(table), type 8 checks AT(p0 + UP), type 15 uses the episode's part and direction, and the
phase counts match the goals.
"""

from __future__ import annotations

from dataclasses import dataclass

from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.tasks.skills import SkillStep

ANY_PART = "*"
"""Goal part meaning 'any part of the object' (GRASPING/TOUCHING of the whole object)."""
FACING_THRESHOLD = 0.5
"""Radians between a part's direction and its goal within which FACING holds (spec 4)."""


@dataclass(frozen=True)
class Goal:
    """One predicate of a task-mode phase. Slots are resolved against an episode's chain.

    kind: 'ON', 'GRASPING', 'TOUCHING', 'FACING', 'AT' or 'RELEASED' (not GRASPING, not TOUCHING, gripper open,
    gripper away from the object: the release effects of spec 5.2).
    part: a part slot ('P1'..'P3') or ANY_PART; direction: a direction slot ('D1', 'D2') for FACING;
    offset: direction slots and literal words summed into the AT target p0 + 0.12 * sum; threshold: metres or radians.
    """

    kind: str
    part: str | None = None
    direction: str | None = None
    offset: tuple[str, ...] = ()
    threshold: float = 0.0


@dataclass(frozen=True)
class StepTemplate:
    name: str
    part: str | None = None
    direction: str | None = None
    grasping: bool = False
    touching: bool = False
    put_down: bool = False


@dataclass(frozen=True)
class TaskType:
    id: int
    chain: tuple[StepTemplate, ...]
    phases: tuple[tuple[Goal, ...], ...]

    @property
    def seen(self) -> bool:
        """Types 1-10 are trained on; 11-16 appear only in Test 4 (spec 6.1)."""
        return self.id <= 10

    @property
    def part_slots(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(s.part for s in self.chain if s.part))

    @property
    def direction_slots(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(s.direction for s in self.chain if s.direction and s.direction.startswith("D")))

    def slots(self, chain) -> tuple[dict[str, str], dict[str, str]]:
        """Invert `build_chain`: the slot values of an episode's chain, or TaskError naming both chains."""
        parts: dict[str, str] = {}
        directions: dict[str, str] = {}
        if [s.name for s in chain] == [t.name for t in self.chain]:
            for template, step in zip(self.chain, chain):
                if template.part:
                    parts.setdefault(template.part, step.part)
                if template.direction in self.direction_slots:
                    directions.setdefault(template.direction, step.direction)
            if self.build_chain(parts, directions) == list(chain):
                return parts, directions
        raise TaskError(f"chain {', '.join(_describe(s) for s in chain)} does not fit task type {self.id} "
                        f"({', '.join(_describe(t) for t in self.chain)})")

    def build_chain(self, parts: dict[str, str], directions: dict[str, str]) -> list[SkillStep]:
        """The skill chain with slots filled; raises TaskError for a missing slot."""
        missing = [s for s in (*self.part_slots, *self.direction_slots) if s not in parts and s not in directions]
        if missing:
            raise TaskError(f"task type {self.id} needs {', '.join(missing)}")
        return [SkillStep(t.name, parts.get(t.part) if t.part else None,
                          directions.get(t.direction, t.direction) if t.direction else None,
                          t.grasping, t.touching, t.put_down) for t in self.chain]


def _describe(step) -> str:
    arguments = [a for a in (step.part, step.direction) if a is not None]
    flags = [f for f in ("grasping", "touching", "put_down") if getattr(step, f)]
    return f"{step.name}({', '.join(arguments + flags)})"


def _grasp(part="P1"):
    return StepTemplate("grasp_obj", part=part)


def _touch(part="P1"):
    return StepTemplate("touch_obj", part=part)


def _carry(direction, put_down=False):
    return StepTemplate("move_gripper", direction=direction, grasping=True, put_down=put_down)


def _push(direction):
    return StepTemplate("move_gripper", direction=direction, touching=True)


def _rotate(direction, part="P2"):
    return StepTemplate("rotate_obj", part=part, direction=direction)


_RELEASE = StepTemplate("release_obj")
ON = Goal("ON")
RELEASED = Goal("RELEASED")


def _at(*offset, threshold):
    return Goal("AT", offset=tuple(offset), threshold=threshold)


def _facing(direction, part="P2"):
    return Goal("FACING", part=part, direction=direction, threshold=FACING_THRESHOLD)


_TYPES = [
    TaskType(1, (_grasp(),), ((Goal("GRASPING", "P1"), ON),)),
    TaskType(2, (_touch(),), ((Goal("TOUCHING", "P1"), ON),)),
    TaskType(3, (_grasp(), _carry("D1")), ((Goal("GRASPING", "P1"), _at("D1", threshold=0.05)),)),
    TaskType(4, (_touch(), _push("D1")), ((Goal("TOUCHING", "P1"), _at("D1", threshold=0.05), ON),)),
    TaskType(5, (_grasp(), _carry("D1"), _RELEASE),
             ((Goal("GRASPING", "P1"), _at("D1", threshold=0.03), ON), (RELEASED,))),
    TaskType(6, (_touch(), _push("D1"), _RELEASE),
             ((Goal("TOUCHING", "P1"), _at("D1", threshold=0.03), ON), (RELEASED,))),
    TaskType(7, (_grasp(), _carry("top"), _carry("D1")), ((Goal("GRASPING", "P1"), _at("top", "D1", threshold=0.05)),)),
    TaskType(8, (_grasp(), _carry("top"), _rotate("D1")),
             ((Goal("GRASPING", ANY_PART), _facing("D1"), _at("top", threshold=0.08)),)),
    TaskType(9, (_grasp(), _carry("top"), _carry("D1"), _carry("bottom", put_down=True)),
             ((Goal("GRASPING", "P1"), _at("top", "D1", threshold=0.08)),
              (Goal("GRASPING", "P1"), _at("D1", threshold=0.08)))),
    TaskType(10, (_grasp(), _carry("top"), _carry("D1"), _rotate("D2")),
             ((Goal("GRASPING", ANY_PART), _facing("D2"), _at("top", "D1", threshold=0.08)),)),
    TaskType(11, (_grasp(), _carry("top"), _rotate("D1"), _carry("bottom", put_down=True)),
             ((Goal("GRASPING", ANY_PART), _facing("D1"), _at("top", threshold=0.08)),
              (Goal("GRASPING", ANY_PART), _facing("D1"), _at(threshold=0.08)))),
    TaskType(12, (_grasp(), _carry("top"), _carry("D1"), _rotate("D2"), _carry("bottom", put_down=True)),
             ((Goal("GRASPING", "P1"), _facing("D2"), _at("top", "D1", threshold=0.08)),
              (Goal("GRASPING", "P1"), _facing("D2"), _at("D1", threshold=0.08)))),
    TaskType(13, (_grasp(), _rotate("D1"), _carry("D2")),
             ((ON, _facing("D1")), (ON, _at("D2", threshold=0.08)))),
    TaskType(14, (_touch(), _push("D1"), _RELEASE, _grasp("P3"), _rotate("D2")),
             ((ON, Goal("TOUCHING", "P1"), _at("D1", threshold=0.05)), (ON, _facing("D2")))),
    TaskType(15, (_grasp(), _rotate("D1")), ((_facing("D1"), ON),)),
    TaskType(16, (_touch(), _push("D1"), _RELEASE, _grasp("P3"), _carry("top"), _rotate("D2"),
                  _carry("bottom", put_down=True)),
             ((_facing("D2"), _at("top", "D1", threshold=0.08)), (_facing("D2"), _at("D1", threshold=0.08)))),
]
TASK_TYPES: dict[int, TaskType] = {t.id: t for t in _TYPES}


def task_type(type_id) -> TaskType:
    """The task type with id 1..16 (int or the metadata's string); raises TaskError otherwise."""
    try:
        return TASK_TYPES[int(type_id)]
    except (KeyError, ValueError, TypeError):
        raise TaskError(f"task type {type_id!r} is out of range; expected 1..16") from None
