"""The five base skills and their parameters, in the original's metadata format (spec 5.1)."""

from __future__ import annotations

from dataclasses import dataclass

from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.tasks.vocabulary import DIRECTIONS

SKILL_NAMES = ("grasp_obj", "touch_obj", "move_gripper", "rotate_obj", "release_obj")
_PART_KEY = {"grasp_obj": "part_grasp", "touch_obj": "part_touch", "rotate_obj": "part_rotate"}


@dataclass(frozen=True)
class SkillStep:
    """One skill of a chain. `part` is a part label ('' = the whole object); `direction` a direction word."""

    name: str
    part: str | None = None
    direction: str | None = None
    grasping: bool = False
    touching: bool = False
    put_down: bool = False

    def __post_init__(self):
        if self.name not in SKILL_NAMES:
            raise TaskError(f"unknown skill '{self.name}'; expected one of {', '.join(SKILL_NAMES)}")
        if (self.name in _PART_KEY) != (self.part is not None):
            raise TaskError(f"skill '{self.name}' {'needs' if self.name in _PART_KEY else 'takes no'} part")
        needs_direction = self.name in ("move_gripper", "rotate_obj")
        if needs_direction != (self.direction is not None):
            raise TaskError(f"skill '{self.name}' {'needs' if needs_direction else 'takes no'} direction")
        if self.direction is not None and self.direction not in DIRECTIONS:
            raise TaskError(f"unknown direction '{self.direction}' in skill '{self.name}'; "
                            f"expected one of {', '.join(DIRECTIONS)}")
        if self.put_down and self.direction != "bottom":
            raise TaskError("move_gripper with put_down must move towards 'bottom'")

    def to_metadata(self) -> dict:
        """{"skill_name": ..., "params": {...}} as in the original's episode JSON (spec 9.2)."""
        params: dict = {}
        if self.name in _PART_KEY:
            params[_PART_KEY[self.name]] = self.part
        if self.name == "move_gripper":
            params = {"dir_move": self.direction, "grasping": self.grasping, "touching": self.touching,
                      "put_down": self.put_down}
        elif self.name == "rotate_obj":
            params["dir_rotate"] = self.direction
        return {"skill_name": self.name, "params": params}

    @classmethod
    def from_metadata(cls, entry: dict) -> SkillStep:
        """Parse one `chain_params` entry; raises TaskError naming what is wrong."""
        try:
            name, params = entry["skill_name"], entry.get("params", {})
        except (KeyError, TypeError):
            raise TaskError(f"a chain entry needs 'skill_name' and 'params', got {entry!r}") from None
        if name not in SKILL_NAMES:
            raise TaskError(f"unknown skill '{name}'; expected one of {', '.join(SKILL_NAMES)}")
        part = params.get(_PART_KEY[name], "") if name in _PART_KEY else None
        direction = params.get("dir_move") if name == "move_gripper" else params.get("dir_rotate")
        return cls(name, part, direction if name in ("move_gripper", "rotate_obj") else None,
                   bool(params.get("grasping", False)), bool(params.get("touching", False)),
                   bool(params.get("put_down", False)))
