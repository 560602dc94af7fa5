"""Skill and task instructions: the original's skill templates (spec 5.3) and task templates with paraphrases.

Skill instructions must match the original exactly (policies tokenise them). Task instructions follow the paper's
appendix templates (the first variant of each type) plus hand-written paraphrases, as the original paraphrased its
templates into 3-8 variants. A task sentence names only the slots its goal checks (parts the task is about, not the
part the robot chooses to hold, e.g. type 8 grasps P1 but the goal is GRASPING(any)); type 15 names no direction.
"""

from __future__ import annotations

import functools
import string

from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.tasks.skills import SkillStep
from partinstruct_mjx.tasks.task_types import task_type
from partinstruct_mjx.tasks.vocabulary import SPATIAL_PARTS

FACE_WORDS = {"front": "front", "back": "back", "top": "upwards", "bottom": "downwards", "left": "left",
              "right": "right"}
"""R(dir) of the rotate skill template: 'to face {R(dir)}'."""

MOVE_WORDS = {"front": "forwards", "back": "backwards", "top": "upwards", "bottom": "downwards",
              "left": "to the left", "right": "to the right"}
"""T(dir) of the move skill template: 'Move {T(dir)}'; also used for 'points {T(dir)}' in task sentences."""

# Placeholders: {obj}, {obj_s} (possessive); {P1} {P2} {P3} part phrases; {D1} {D2} as MOVE_WORDS ("to the left");
# {D1_face} {D2_face} as FACE_WORDS ("left"). The first variant of each type is the paper's template.
TASK_TEMPLATES: dict[int, tuple[str, ...]] = {
    1: ("Grasp the {obj} by the {P1}",
        "Take hold of the {obj} at its {P1}",
        "Grab the {obj} by its {P1} and leave it on the table",
        "Close the gripper on the {P1} of the {obj}",
        "Get a firm grip on the {obj_s} {P1} without lifting it",
        "Hold the {obj} by the {P1}"),
    2: ("Touch the {obj} at the {P1}",
        "Make contact with the {P1} of the {obj}",
        "Reach out and touch the {obj_s} {P1}",
        "Rest the closed gripper against the {P1} of the {obj}",
        "Put the tip of the gripper on the {obj} at its {P1}",
        "Place the gripper so it touches the {P1} of the {obj}"),
    3: ("Hold the {P1} of the {obj} and move it {D1}",
        "Grasp the {obj} by its {P1} and shift it {D1}",
        "Holding the {obj} by the {P1}, move it {D1}",
        "Grip the {obj_s} {P1} and bring it {D1}",
        "Take the {obj} at its {P1} and move it {D1}",
        "With the {P1} of the {obj} in the gripper, shift the {obj} {D1}"),
    4: ("Push the {obj} {D1} by touching the {P1}",
        "Touch the {P1} of the {obj} and push it {D1}",
        "With the gripper against the {obj_s} {P1}, push the {obj} {D1}",
        "Nudge the {obj} {D1}, pressing against its {P1}",
        "Press on the {P1} of the {obj} to slide it {D1}",
        "Make the {obj} move {D1} by pushing at its {P1}"),
    5: ("Slide the {obj} on the table {D1} while keeping hold of the {P1}, then release it",
        "Holding the {obj} by its {P1}, drag it {D1} along the table and let go",
        "Grasp the {P1} of the {obj}, slide it {D1} across the table, then release it",
        "Keep a grip on the {obj_s} {P1} while sliding it {D1} on the table, then let it go",
        "Drag the {obj} {D1} over the table by its {P1} and release it",
        "Move the {obj} {D1} along the table surface, holding the {P1}, and then open the gripper"),
    6: ("Move the {obj} {D1} by pushing it at the {P1}, then free it",
        "Push the {obj} {D1} at its {P1}, then let go of it",
        "Press against the {P1} of the {obj} to push it {D1}, then move the gripper away",
        "Shove the {obj} {D1} by its {P1} and release it afterwards",
        "Touch the {obj_s} {P1}, push it {D1}, then back off",
        "Slide the {obj} {D1} by pressing on the {P1}, and then take the gripper off it"),
    7: ("While keeping hold of the {P1}, move the {obj} {D1} in the air",
        "Lift the {obj} by its {P1} and move it {D1} in the air",
        "Holding the {P1}, raise the {obj} and carry it {D1}",
        "Pick up the {obj} by the {P1} and carry it {D1} without putting it down",
        "Grip the {obj_s} {P1}, lift it off the table and shift it {D1}",
        "Raise the {obj} by the {P1} and keep it in the air while moving it {D1}"),
    8: ("Rotate the {P2} of the {obj} to face {D1_face} while lifting it",
        "Lift the {obj} and turn it so that its {P2} points {D1}",
        "Pick up the {obj} and reorient it until the {P2} faces {D1_face}",
        "Raise the {obj} off the table, rotating it so its {P2} is pointing {D1}",
        "While holding the {obj} up in the air, turn its {P2} to face {D1_face}",
        "Hold the {obj} above the table with its {P2} facing {D1_face}"),
    9: ("Move the {obj} {D1} after raising it, while keeping hold of the {P1}, then put it down",
        "Lift the {obj} by its {P1}, carry it {D1} and set it back down",
        "Holding the {P1}, raise the {obj}, move it {D1} and put it down again",
        "Pick the {obj} up by the {P1}, shift it {D1} through the air, then place it on the table",
        "Grip the {obj_s} {P1}, lift it, bring it {D1} and lower it onto the table",
        "Using the {P1} as the grip, move the {obj} {D1} through the air and put it back on the table"),
    10: ("Move the {obj} {D1} in the air, then rotate the {P2} to point {D2}",
         "Lift the {obj}, carry it {D1}, and turn it so the {P2} faces {D2_face}",
         "Raise the {obj}, shift it {D1}, then reorient it until its {P2} points {D2}",
         "Pick up the {obj}, move it {D1} while it is in the air, and rotate the {P2} to face {D2_face}",
         "Holding the {obj} above the table, bring it {D1} and then make its {P2} point {D2}",
         "Carry the {obj} {D1} through the air and finish with its {P2} facing {D2_face}"),
    11: ("Rotate the {P2} of the {obj} in the air so it points {D1}, then put it down",
         "Lift the {obj}, turn it so its {P2} faces {D1_face}, and set it back on the table",
         "Pick up the {obj}, reorient the {P2} to point {D1} and place the {obj} down again",
         "Holding the {obj} in the air, rotate it until the {P2} is facing {D1_face}, then lower it onto the table",
         "Raise the {obj}, make its {P2} point {D1}, then put it back down",
         "Turn the {obj} in mid-air so the {P2} faces {D1_face}, and then set it down"),
    12: ("Shift the {obj} {D1} in the air while grasping the {P1}, turn the {P2} to face {D2_face}, then set it down",
         "Holding the {obj} by its {P1}, lift it, move it {D1}, rotate it so the {P2} points {D2}, and put it down",
         "Grasp the {P1} of the {obj}, carry it {D1} through the air, turn its {P2} to face {D2_face}, "
         "then lower it onto the table",
         "With a grip on the {obj_s} {P1}, raise it and bring it {D1}, make the {P2} point {D2}, "
         "and finally set it down",
         "Lift the {obj} by the {P1}, shift it {D1}, make the {P2} face {D2_face}, then place it on the table",
         "Keeping hold of the {P1}, move the {obj} {D1} in the air, reorient its {P2} to face {D2_face}, "
         "and put it back down"),
    13: ("Turn the {P2} of the {obj} to point {D1} while keeping it on the table, then push it {D2}",
         "Keeping the {obj} on the table, rotate it until its {P2} faces {D1_face}, then slide it {D2}",
         "Without lifting the {obj}, turn its {P2} to point {D1}, and afterwards move it {D2}",
         "On the table, reorient the {obj} so the {P2} points {D1}, then shift it {D2}",
         "Spin the {obj} on the table so that its {P2} faces {D1_face}, then move it {D2} along the table",
         "Rotate the {obj} in place on the table until the {P2} points {D1}, and then push it {D2}"),
    14: ("While keeping it on the table, push the {obj} {D1} while touching the {P1}, then rotate the {P2} "
         "to face {D2_face}",
         "Push the {obj} {D1} by touching its {P1}, then, keeping it on the table, turn it so the {P2} points {D2}",
         "Slide the {obj} {D1} by pressing on the {P1}, then rotate it on the table until the {P2} faces {D2_face}",
         "Touching the {P1}, push the {obj} {D1} along the table, and then reorient its {P2} to point {D2} "
         "without lifting it",
         "Nudge the {obj} {D1} at its {P1}, then spin it on the table so its {P2} faces {D2_face}",
         "Press against the {obj_s} {P1} to push it {D1}, then turn it on the table so the {P2} faces {D2_face}"),
    15: ("Rotate the {P2} of the {obj} to face the opposite direction",
         "Turn the {obj} on the table so that its {P2} points the opposite way",
         "Reorient the {obj} until its {P2} faces the opposite way",
         "Keeping the {obj} on the table, make its {P2} point in the opposite direction",
         "Spin the {obj} around so the {P2} faces away from where it faces now",
         "Rotate the {obj} in place so that its {P2} ends up pointing the other way"),
    16: ("Push the {obj} {D1} and rotate the {P2} to point {D2} in the air, finally place it down",
         "Push the {obj} {D1}, then lift it, turn its {P2} to face {D2_face}, and put it back down",
         "First slide the {obj} {D1} by pushing it, then raise it, rotate it so the {P2} points {D2}, and set it down",
         "Shove the {obj} {D1}, pick it up, reorient the {P2} to face {D2_face} in the air, "
         "and lower it onto the table",
         "After pushing the {obj} {D1}, lift it and turn it until its {P2} points {D2}, then place it on the table",
         "Nudge the {obj} {D1}, then raise it, make its {P2} face {D2_face}, and set it back on the table"),
}


def skill_instruction(step: SkillStep, obj_class: str) -> str:
    """The original's skill-instruction template for one step (spec 5.3); part '' (whole object) drops 'at its'."""
    if step.name == "release_obj":
        return "Release"
    if step.name == "move_gripper":
        return f"Move {MOVE_WORDS[step.direction]}"
    if step.name == "rotate_obj":
        subject = f"the {step.part} of the {obj_class}" if step.part else f"the {obj_class}"
        return f"Reorient {subject} to face {FACE_WORDS[step.direction]}"
    verb = "Grasp" if step.name == "grasp_obj" else "Touch"
    return f"{verb} the {obj_class} at its {step.part}" if step.part else f"{verb} the {obj_class}"


@functools.lru_cache(maxsize=None)
def instruction_slots(type_id: int) -> tuple[str, ...]:
    """Slots ('P1', 'D1', ...) that the task sentences of a type name, in template order."""
    fields = [name for _, name, _, _ in string.Formatter().parse(TASK_TEMPLATES[task_type(type_id).id][0]) if name]
    return tuple(dict.fromkeys(name.removesuffix("_face") for name in fields if not name.startswith("obj")))


def part_phrase(part: str) -> str:
    """How a task sentence names a part: 'handle', 'left part' (spatial words read as regions)."""
    return f"{part} part" if part in SPATIAL_PARTS else part


def task_instruction(type_id, obj_class: str, parts: dict[str, str], directions: dict[str, str], seed: int) -> str:
    """A task sentence for the filled slots; the variant is `seed` modulo the number of variants."""
    variants = TASK_TEMPLATES[task_type(type_id).id]
    missing = [slot for slot in instruction_slots(type_id) if slot not in parts and slot not in directions]
    if missing:
        raise TaskError(f"task type {type_id} instruction needs {', '.join(missing)}")
    values = {"obj": obj_class, "obj_s": obj_class + ("'" if obj_class.endswith("s") else "'s")}
    values.update({slot: part_phrase(part) for slot, part in parts.items()})
    for slot, word in directions.items():
        if word not in MOVE_WORDS:
            raise TaskError(f"unknown direction '{word}' for {slot}; expected one of {', '.join(MOVE_WORDS)}")
        values[slot], values[f"{slot}_face"] = MOVE_WORDS[word], FACE_WORDS[word]
    return variants[seed % len(variants)].format(**values)
