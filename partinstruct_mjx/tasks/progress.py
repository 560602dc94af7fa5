"""Success checking: episodes compiled to goal rows, evaluated every step in JAX (skill mode and task mode, spec 7).

A goal row is one predicate with its arguments; every skill of a chain and every task-mode phase is a fixed number
of rows (padding rows always hold), so a batch can mix task types and chain lengths in one jitted update.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.tasks import predicates
from partinstruct_mjx.tasks.part_geometry import PartGeometry, PartNames, spatial_masks
from partinstruct_mjx.tasks.skills import SkillStep
from partinstruct_mjx.tasks.task_types import ANY_PART, TASK_TYPES, Goal, task_type
from partinstruct_mjx.tasks.vocabulary import UNIT_DISTANCE, direction_vector

GOAL_KINDS = ("PAD", "ON", "GRASPING", "TOUCHING", "FACING", "AT", "RELEASED")
MAX_GOALS = 4
MAX_SKILLS = 7
MAX_PHASES = 2
MOVE_THRESHOLD = 0.05
FROZEN_SPATIAL_TYPES = tuple(t.id for t in TASK_TYPES.values() if any(s.name == "rotate_obj" for s in t.chain))
"""Task mode keeps the spatial parts of the types that turn the object (8, 10-16) as sampled at reset (spec 3.3). The
original's list also names 17, which does not exist, and leaves out 11, a rotation task: a spatial part resampled
every step always lies on its own side, so 'rotate the back to face left' could never hold (docs/differences.md)."""
PROGRESS_FIELDS = ("skill_index", "phase", "skill_p0", "masks", "goals_met", "success", "completion")
"""The TaskState fields `update` changes (the others are fixed at reset)."""


@struct.dataclass
class GoalRows:
    """Predicates to hold together. kind: index into GOAL_KINDS; part: part row; direction: FACING axis;
    offset: AT target relative to p0; threshold: AT distance or FACING angle. Leading dims are free."""

    kind: jnp.ndarray
    part: jnp.ndarray
    direction: jnp.ndarray
    offset: jnp.ndarray
    threshold: jnp.ndarray


@struct.dataclass
class TaskState:
    """Per-environment progress (batch first)."""

    skills: GoalRows
    num_skills: jnp.ndarray
    phases: GoalRows
    num_phases: jnp.ndarray
    freeze_spatial: jnp.ndarray
    skill_index: jnp.ndarray
    phase: jnp.ndarray
    skill_p0: jnp.ndarray
    task_p0: jnp.ndarray
    masks: jnp.ndarray
    goals_met: jnp.ndarray
    """(B, MAX_GOALS) the current skill's (skill mode) or phase's (task mode) predicates at the last step."""
    success: jnp.ndarray
    completion: jnp.ndarray


def _empty_rows(*shape) -> dict[str, np.ndarray]:
    return {"kind": np.zeros(shape, np.int32), "part": np.zeros(shape, np.int32),
            "direction": np.zeros((*shape, 3), np.float32), "offset": np.zeros((*shape, 3), np.float32),
            "threshold": np.zeros(shape, np.float32)}


def _fill(rows: dict, index: tuple, goals: list[tuple]) -> None:
    if len(goals) > MAX_GOALS:
        raise TaskError(f"{len(goals)} predicates exceed the {MAX_GOALS} a skill or phase may hold")
    for g, (kind, part, direction, offset, threshold) in enumerate(goals):
        rows["kind"][(*index, g)] = GOAL_KINDS.index(kind)
        rows["part"][(*index, g)] = part
        rows["direction"][(*index, g)] = direction
        rows["offset"][(*index, g)] = offset
        rows["threshold"][(*index, g)] = threshold


def skill_goals(step: SkillStep, names: PartNames) -> list[tuple]:
    """The effects of one skill (spec 5.2) as goal tuples (kind, part, direction, offset, threshold)."""
    zero, whole = np.zeros(3), names.whole
    if step.name == "grasp_obj":
        return [("GRASPING", names.index(step.part), zero, zero, 0.0)]
    if step.name == "touch_obj":
        return [("TOUCHING", names.index(step.part), zero, zero, 0.0)]
    if step.name == "rotate_obj":
        return [("GRASPING", whole, zero, zero, 0.0),
                ("FACING", names.index(step.part), direction_vector(step.direction), zero, predicates.FACING_ANGLE)]
    if step.name == "release_obj":
        return [("RELEASED", whole, zero, zero, 0.0)]
    goals = []
    if step.grasping:
        goals.append(("GRASPING", whole, zero, zero, 0.0))
        if step.put_down:
            goals.append(("ON", whole, zero, zero, 0.0))
    if step.touching:
        goals.append(("TOUCHING", whole, zero, zero, 0.0))
    if not step.put_down:
        goals.append(("AT", whole, zero, UNIT_DISTANCE * direction_vector(step.direction), MOVE_THRESHOLD))
    return goals


def phase_goals(goal: Goal, parts: dict, directions: dict, names: PartNames) -> tuple:
    zero = np.zeros(3)
    part = names.whole if goal.part in (None, ANY_PART) else names.index(parts[goal.part])
    if goal.kind == "FACING":
        return ("FACING", part, direction_vector(directions[goal.direction]), zero, goal.threshold)
    if goal.kind == "AT":
        offset = sum((direction_vector(directions.get(w, w)) for w in goal.offset), zero)
        return ("AT", part, zero, UNIT_DISTANCE * offset, goal.threshold)
    return (goal.kind, part, zero, zero, goal.threshold)


def compile_episodes(episodes: list[tuple[int, list[SkillStep]]], names: PartNames) -> dict:
    """Host arrays of skill goals, phase goals and flags for (task type, chain) pairs; validates every part."""
    batch = len(episodes)
    skills, phases = _empty_rows(batch, MAX_SKILLS, MAX_GOALS), _empty_rows(batch, MAX_PHASES, MAX_GOALS)
    num_skills, num_phases = np.zeros(batch, np.int32), np.zeros(batch, np.int32)
    freeze = np.zeros(batch, bool)
    for b, (type_id, chain) in enumerate(episodes):
        parts, directions = task_type(type_id).slots(chain)
        if len(chain) > MAX_SKILLS:
            raise TaskError(f"a chain of {len(chain)} skills exceeds {MAX_SKILLS}")
        for s, step in enumerate(chain):
            _fill(skills, (b, s), skill_goals(step, names))
        task = task_type(type_id)
        for p, goals in enumerate(task.phases):
            _fill(phases, (b, p), [phase_goals(g, parts, directions, names) for g in goals])
        num_skills[b], num_phases[b] = len(chain), len(task.phases)
        freeze[b] = type_id in FROZEN_SPATIAL_TYPES
    return {"skills": skills, "phases": phases, "num_skills": num_skills, "num_phases": num_phases,
            "freeze_spatial": freeze}


def evaluate(state, geo: PartGeometry, masks: jnp.ndarray, rows: GoalRows, p0: jnp.ndarray,
             facts: predicates.PartFacts | None = None) -> jnp.ndarray:
    """(G,) truth of each goal row for one environment; padding rows are true. `facts` are
    `predicates.part_facts(state, geo, masks)` when the caller has them (a batch computes them with fewer searches)."""
    facts = predicates.part_facts(state, geo, masks) if facts is None else facts
    released = (~facts.grasped[geo.whole] & ~facts.touched[geo.whole] & predicates.gripper_open(state)
                & predicates.min_distance(state))

    def one(kind, part, direction, offset, threshold):
        values = jnp.stack([
            jnp.asarray(True),
            facts.on_table,
            facts.grasped[part],
            facts.touched[part],
            predicates.points_along(facts.centers[part] - state.object_pos, direction, threshold),
            predicates.at_position(state, p0 + offset, threshold),
            released,
        ])
        return values[kind]

    return jax.vmap(one)(rows.kind, rows.part, rows.direction, rows.offset, rows.threshold)


def _current_masks(state, geo):
    return spatial_masks(predicates.object_points(state, geo))


def _batch_masks(state, geo):
    return jax.vmap(_current_masks, in_axes=(0, None))(state, geo)


def initial_task_state(state, geo: PartGeometry, compiled: dict) -> TaskState:
    """Progress at reset: first skill, first phase, p0 = object position, spatial parts sampled now."""
    masks = _batch_masks(state, geo)
    batch = masks.shape[0]
    position = jnp.asarray(state.object_pos, jnp.float32)
    return TaskState(
        skills=GoalRows(**{k: jnp.asarray(v) for k, v in compiled["skills"].items()}),
        num_skills=jnp.asarray(compiled["num_skills"]),
        phases=GoalRows(**{k: jnp.asarray(v) for k, v in compiled["phases"].items()}),
        num_phases=jnp.asarray(compiled["num_phases"]),
        freeze_spatial=jnp.asarray(compiled["freeze_spatial"]),
        skill_index=jnp.zeros(batch, jnp.int32), phase=jnp.zeros(batch, jnp.int32),
        skill_p0=position, task_p0=position, masks=masks,
        goals_met=jnp.zeros((batch, MAX_GOALS), bool), success=jnp.zeros(batch, bool),
        completion=jnp.zeros(batch, jnp.float32))


def _resampled(keep: jnp.ndarray, masks: jnp.ndarray, state, geo) -> jnp.ndarray:
    """Spatial masks resampled where `keep` (B,) is false; computed only when some environment needs them."""
    return jax.lax.cond(keep.all(), lambda: masks,
                        lambda: jnp.where(keep[:, None, None], masks, _batch_masks(state, geo)))


def rows_at(rows: GoalRows, index: jnp.ndarray) -> GoalRows:
    """(B, G) rows: each environment's rows (B, S, G) at its `index` (B,)."""
    return jax.vmap(lambda r, i: jax.tree_util.tree_map(lambda x: x[i], r))(rows, index)


def goal_facts(state, geo: PartGeometry, masks, rows: GoalRows) -> predicates.PartFacts:
    """The batch's part facts for evaluating `rows` (B, G): each search only when one of the rows reads it."""
    def kind(name):
        return rows.kind == GOAL_KINDS.index(name)

    spatial = (rows.part >= geo.num_semantic) & (rows.part < geo.whole)
    return predicates.batch_part_facts(state, geo, masks, regions=(kind("GRASPING") & spatial).any(),
                                       tips=(kind("TOUCHING") | kind("RELEASED")).any(), centers=kind("FACING").any(),
                                       table=kind("ON").any())


def _skill_update(task: TaskState, state, geo):
    def one(task, state, rows, facts):
        met = evaluate(state, geo, task.masks, rows, task.skill_p0, facts)
        finished = met.all() & ~task.success
        skill_index = task.skill_index + finished
        p0 = jnp.where(finished, state.object_pos, task.skill_p0)
        success = skill_index >= task.num_skills
        return finished, task.replace(skill_index=skill_index, skill_p0=p0, goals_met=met, success=success,
                                      completion=skill_index / task.num_skills)

    rows = rows_at(task.skills, jnp.minimum(task.skill_index, MAX_SKILLS - 1))
    finished, task = jax.vmap(one)(task, state, rows, goal_facts(state, geo, task.masks, rows))
    return task.replace(masks=_resampled(~finished, task.masks, state, geo))  # resampled when the next skill starts


def _task_update(task: TaskState, state, geo):
    def one(task, state, masks, rows, facts):
        met = evaluate(state, geo, masks, rows, task.task_p0, facts)
        real = rows.kind > 0
        holds = met.all() & ~task.success
        last = task.phase == task.num_phases - 1
        sizes = (task.phases.kind > 0).sum(axis=-1)
        done_before = jnp.where(task.phase > 0, sizes[0], 0)
        completion = (done_before + (met & real).sum()) / sizes[: MAX_PHASES].sum(where=jnp.arange(MAX_PHASES)
                                                                                 < task.num_phases)
        success = task.success | (holds & last)
        phase = task.phase + (holds & ~last)
        return task.replace(masks=masks, phase=phase, goals_met=met, success=success,
                            completion=jnp.where(success, 1.0, completion))

    masks = _resampled(task.freeze_spatial, task.masks, state, geo)
    rows = rows_at(task.phases, task.phase)
    return jax.vmap(one)(task, state, masks, rows, goal_facts(state, geo, masks, rows))


def update(task: TaskState, state, geo: PartGeometry, skill_mode: bool) -> TaskState:
    """Advance every environment's progress after a step (skill mode: chain of skill effects; task mode: phases)."""
    return _skill_update(task, state, geo) if skill_mode else _task_update(task, state, geo)
