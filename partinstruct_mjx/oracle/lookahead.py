"""Look-ahead for grasps: can the arm carry out the rest of the chain holding the object this way?

A grasp decides everything the hand does until the release: carries move the hand with the object, a rotation turns
it. `outlook` follows the chain after the grasp with the object rigid in the hand (moves: the hand shifts by the
unit distance; a put-down: back to the grasp height; a rotation: the turn rotation.py would choose), checking with the
batched IK that each hand pose is reachable, each from the previous solution, and whether that turn fits the task
(rotation.TurnPlan.fits). The planner prefers grasps whose outlook is clear and, of those, grasps whose turn fits: a
grasp across a bottle that leaves no wrist range for the turn the task needs fails only later, and a box held from
above and turned upside down in the air ends with the hand under it, too high for the AT goal after the turn.
Pure JAX for one environment and one grasp.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from partinstruct_mjx.control import jax_ik
from partinstruct_mjx.oracle import rotation
from partinstruct_mjx.oracle.kinds import MOVE, RELEASE, ROTATE
from partinstruct_mjx.tasks.vocabulary import UNIT_DISTANCE

REACH_CONFIG = jax_ik.IKConfig(iterations=30)
CLEAR_AND_FITS, CLEAR, BLOCKED = 0, 1, 2
"""`outlook`'s tiers, best first."""


def reach_all(kinematics, q, positions, quat, config=REACH_CONFIG, counts=None):
    """Whether the IK reaches every TCP position (N, 3) at orientation `quat` in turn, each from the previous
    solution (positions where `counts` (N,) is False are skipped); and the joint angles at the last one reached.
    One IK in a scan, so the compiled graph holds a single solver."""
    counts = jnp.ones(positions.shape[0], bool) if counts is None else counts

    def visit(carry, item):
        joints, ok = carry
        position, counted = item
        reached, hit = rotation.reach(kinematics, config, joints, position, quat)
        return (jnp.where(counted, reached, joints), ok & (hit | ~counted)), None

    (joints, ok), _ = jax.lax.scan(visit, (q, jnp.asarray(True)), (positions, counts))
    return ok, joints


def outlook(kinematics, q, hand_pos, hand_quat, chain: dict, start, object_pos, object_points, object_valid,
            part_vector) -> jnp.ndarray:
    """The grasp's rank tier: CLEAR_AND_FITS when every hand pose of the skills after skill `start` (a grasp) up to the
    next release is reachable and the turn among them (if any) fits the task, CLEAR when they are only reachable,
    BLOCKED otherwise.

    q: joint angles at the grasp; hand_pos/hand_quat: the grasp's TCP pose; chain: the episode's compiled chain
    (machine.OracleState fields kind, direction, put_down, part rows, on_table_turn, num_skills as (S, ...) arrays);
    part_vector: a function part row -> the part's direction from the object origin now (FACING's vector).
    """
    size = chain["kind"].shape[0]
    index = jnp.clip(start + jnp.arange(1, size), 0, size - 1)
    kinds = jnp.where(start + jnp.arange(1, size) < chain["num_skills"], chain["kind"][index], RELEASE)
    held = jnp.cumsum(kinds == RELEASE) == 0
    moves, turns = held & (kinds == MOVE), held & (kinds == ROTATE)
    put_down = chain["put_down"][index]
    # Hand shifts of the moves: a carry by the unit distance, a put-down back down by what the carries raised.
    carries = jnp.where((moves & ~put_down)[:, None], UNIT_DISTANCE * chain["direction"][index], 0.0)
    raised = jnp.cumsum(carries[:, 2]) - carries[:, 2]
    shifts = jnp.where(put_down[:, None], jnp.array([0.0, 0.0, -1.0]) * raised[:, None], carries)
    shifts = jnp.where(moves[:, None], shifts, 0.0)
    has_turn = turns.any()
    first_turn = jnp.argmax(turns)
    before = moves & ((jnp.arange(size - 1) < first_turn) | ~has_turn)
    after = moves & has_turn & (jnp.arange(size - 1) > first_turn)

    # The moves before the turn (all of them without one), each reachable.
    path = hand_pos + jnp.cumsum(jnp.where(before[:, None], shifts, 0.0), axis=0)
    ok, q = reach_all(kinematics, q, path, hand_quat, counts=before)
    pos = path[-1]
    turn_row = index[first_turn]
    moved = pos - hand_pos
    found, axis, angle, pivot, raise_by, q_turned, fits = rotation.plan(
        kinematics, q, pos, hand_quat, object_pos + moved, object_points + moved, object_valid,
        part_vector(chain["part"][turn_row]), chain["direction"][turn_row], chain["on_table_turn"][turn_row],
        (after & put_down).any())
    turned_pos, turned_quat = rotation.turned_pose(pivot, axis, angle, 1.0, pos, hand_quat)
    turned_pos = turned_pos + jnp.array([0.0, 0.0, 1.0]) * raise_by
    # The moves after the turn (a put-down), from the pose the turn ends in.
    path = turned_pos + jnp.cumsum(jnp.where(after[:, None], shifts, 0.0), axis=0)
    ok_after, _ = reach_all(kinematics, q_turned, path, turned_quat, counts=after)
    clear = ok & (~has_turn | (found & ok_after))
    return jnp.where(clear, jnp.where(~has_turn | fits, CLEAR_AND_FITS, CLEAR), BLOCKED)
