"""Rotation plans: which turn of the held object brings a part's direction onto a goal, and which turn the arm can make.

FACING holds for every rotation that maps the part's direction v (from the object origin to the part's mean point)
onto the goal d: the shortest arc from v to d followed by any twist about d. In the air the oracle considers
NUM_TWISTS of them, each about two pivots (the object's origin, which keeps the object where the carries put it, and
the TCP, which keeps the hand where it is); on the table only yaw turns keep the object standing, the short way round
or the long way, each about the middle of the object's footprint (the object spins in place; turned about the TCP of
an off-centre grasp, a standing bottle was dragged round on the table and twisted out of the fingers) or the TCP. The
hand follows the object rigidly, so a turn R about pivot k takes the TCP pose (p, q) to (k + R (p - k), R q). An
option is kept when the batched JAX IK reaches the TCP at every sixth of the way along it, each from the previous
solution without a joint jumping, and the turned object and hand stay above the table (the hand is raised for them
where needed); the cheapest kept option (turn angle, object displacement, raise) wins. Where a put-down follows the
turn, options after which it cannot be made rank last: the arm must reach the way down until the turned object's
lowest point meets the table or the hand (wide along the fingers' closing axis) meets it first, and the object's
origin must then be near the height it rested at (the put-down's AT measures it from there); of the others, those
that leave the object on the table rank first. The plan also says whether the chosen turn fits the task
(TurnPlan.fits), which the grasp look-ahead ranks grasps by; a turn that fits ranks before one that does not. Pure
JAX for one environment.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.control import jax_ik
from partinstruct_mjx.control.rotations import axis_angle_to_quat, quat_multiply, quat_rotate
from partinstruct_mjx.oracle import pushing
from partinstruct_mjx.sim.scene import TABLE_HEIGHT

NUM_TWISTS = 8
"""Twists about the goal direction tried in the air (evenly spaced)."""
TABLE_CLEARANCE = 0.02
"""Lowest point of an object turned in the air stays this far above the table (m)."""
MAX_DISPLACEMENT = 0.05
"""Object origin displacement (m) beyond which an option is penalised hard (AT checks allow 0.05-0.08)."""
REACH_CONFIG = jax_ik.IKConfig(iterations=15)
FRACTIONS = tuple(k / 6.0 for k in range(1, 7))
"""Points along a turn where the IK must reach the TCP, each from the previous solution."""
MAX_JOINT_JUMP = 0.8
"""Largest joint change (rad) between two of those points: the env's IK follows the turn in small steps, so a
solution that only an elbow or wrist flip reaches is not one the arm can turn through."""
UP = np.array([0.0, 0.0, 1.0], np.float32)
PUT_DOWN_FRACTIONS = np.array([0.5, 1.0], np.float32)
"""Points along a put-down after the turn where the IK must reach the TCP."""
PUT_DOWN_SLACK = 0.01
"""How far (m) below the table top the hand's bounding spheres (HAND_SPHERES) may go in a put-down after the turn
(they bound the hand loosely)."""
MAX_RESTING_CHANGE = 0.06
"""Largest difference (m) between the height above the table at which a put-down after the turn leaves the object's
origin (the object on the table, or held where the hand meets the table) and the height it rested at (the put-down's
AT allows 0.08 from the origin before the lift)."""
MAX_LIFT = 0.05
"""Height (m) above where it was that an object turned in the air may end and still meet the AT goal after the turn
(0.08 m), with room for the carries' tolerance."""
CARRY_BACK_START = 0.03
"""A turn about the TCP that moves the object's origin more than this (m) is followed by a carry back (the machine's
RECENTRE_START), which the arm must reach for the turn to fit the task."""
CARRY_BACK_FRACTIONS = np.array([0.5, 1.0], np.float32)
"""Points along the carry back where the IK must reach the TCP."""
UNFIT_COST = 1.0
"""Cost added to a turn that does not fit the task (TurnPlan.fits), so that one that does comes first."""
UNSETTLED_COST = 5.0
"""Cost added to a turn after which the put-down cannot be made (more than the other costs of any turn that keeps
the object within MAX_DISPLACEMENT)."""
HELD_COST = 0.5 * UNSETTLED_COST
"""Cost added to a turn after which the put-down ends with the hand on the table and the object held above it, so
that a put-down onto the table comes first (in skill mode the put-down counts only with the object on the table)."""
HAND_SPHERES = np.array([[0.0, 0.085, -0.02, 0.028], [0.0, -0.085, -0.02, 0.028], [0.0, 0.0, -0.082, 0.045],
                         [0.0, 0.0, -0.192, 0.045]], np.float32)
"""Spheres (centre in the TCP frame, radius) bounding the hand's palm capsule and the last link's, which a turn in
the air keeps above the table too: a mug turned upside down by its rim about its origin would have put the palm
under the table top, and the arm, stopped by the table, never finished the turn (type 16)."""


def arc(v: jnp.ndarray, d: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Axis (3,) and angle of the shortest rotation taking unit vector v onto unit vector d (any perpendicular axis,
    preferring a horizontal one, when they are opposite)."""
    axis = jnp.cross(v, d)
    norm = jnp.linalg.norm(axis)
    angle = jnp.arctan2(norm, v @ d)
    fallback = jnp.cross(v, jnp.asarray(UP))
    fallback = jnp.where(jnp.linalg.norm(fallback) < 1e-3, jnp.cross(v, jnp.array([1.0, 0.0, 0.0])), fallback)
    axis = jnp.where(norm < 1e-4, fallback, axis)
    return axis / jnp.linalg.norm(axis), angle


def quat_to_axis_angle(q: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Unit axis and angle in [0, pi] of a unit quaternion (w, x, y, z)."""
    q = jnp.where(q[0] < 0, -q, q)
    s = jnp.linalg.norm(q[1:])
    angle = 2.0 * jnp.arctan2(s, q[0])
    axis = jnp.where(s < 1e-8, jnp.asarray(UP), q[1:] / jnp.maximum(s, 1e-8))
    return axis, angle


def options(v: jnp.ndarray, d: jnp.ndarray, on_table: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Candidate turns: axes (N, 3), angles (N,) and validity (N,), N = 2 * NUM_TWISTS.

    In the air: each twist about d after the shortest arc, once per pivot (rows [:NUM_TWISTS] about the object's
    origin, the rest about the TCP). On the table: the yaw turn the short way and the long way, once per pivot (the
    footprint's middle, the TCP).
    """
    v = v / jnp.maximum(jnp.linalg.norm(v), 1e-9)
    arc_axis, arc_angle = arc(v, d)
    arc_quat = axis_angle_to_quat(arc_axis, arc_angle)
    twists = jnp.asarray(np.arange(NUM_TWISTS) * 2 * math.pi / NUM_TWISTS, jnp.float32)
    quats = jax.vmap(lambda phi: quat_multiply(axis_angle_to_quat(d, phi), arc_quat))(twists)
    air_axes, air_angles = jax.vmap(quat_to_axis_angle)(quats)
    # Yaw on the table: signed angle from v to d in the horizontal plane, and the long way round.
    yaw = jnp.arctan2(v[0] * d[1] - v[1] * d[0], v[0] * d[0] + v[1] * d[1])
    long_way = yaw - 2 * math.pi * jnp.sign(yaw)
    yaws = jnp.zeros(NUM_TWISTS).at[0].set(yaw).at[1].set(long_way)
    table_axes = jnp.tile(jnp.asarray(UP), (NUM_TWISTS, 1)) * jnp.sign(yaws + 1e-9)[:, None]
    table_valid = jnp.arange(NUM_TWISTS) < 2
    axes = jnp.where(on_table, jnp.concatenate([table_axes, table_axes]), jnp.concatenate([air_axes, air_axes]))
    angles = jnp.where(on_table, jnp.concatenate([jnp.abs(yaws), jnp.abs(yaws)]),
                       jnp.concatenate([air_angles, air_angles]))
    valid = jnp.where(on_table, jnp.concatenate([table_valid, table_valid]),
                      jnp.ones(2 * NUM_TWISTS, bool))
    return axes, angles, valid


def turned_pose(pivot, axis, angle, fraction, hand_pos, hand_quat):
    """TCP pose after turning `fraction` of the way about `axis` through `pivot`."""
    turn = axis_angle_to_quat(axis, fraction * angle)
    pos = pivot + quat_rotate(turn, hand_pos - pivot)
    quat = quat_multiply(turn, hand_quat)
    return pos, quat / jnp.linalg.norm(quat)


def hand_bottom(pos, quat):
    """Height of the lowest point of the hand's bounding spheres (HAND_SPHERES) with the TCP at pose (pos, quat)."""
    centres = pos + quat_rotate(quat[None], HAND_SPHERES[:, :3])
    return (centres[:, 2] - HAND_SPHERES[:, 3]).min()


REACHED_POSITION = 0.005
REACHED_ROTATION = 0.05
"""An IK solve reaches a TCP pose when it ends within this many metres and radians of it."""


def reach(kinematics, config, joints, pos, quat):
    """The IK from `joints` to the TCP pose (pos, quat): the joints it ends at, and whether it got there."""
    reached, position_error, rotation_error = jax_ik._solve_one(kinematics, config, joints, pos, quat)
    return reached, (position_error < REACHED_POSITION) & (rotation_error < REACHED_ROTATION)


def _reach_step(kinematics, joints, ok, pos, quat):
    """`reach` from `joints`: the joints reached, and `ok` still holding if it got there without a joint jumping
    (MAX_JOINT_JUMP)."""
    reached, hit = reach(kinematics, REACH_CONFIG, joints, pos, quat)
    return reached, ok & hit & (jnp.abs(reached - joints).max() < MAX_JOINT_JUMP)


class TurnPlan(NamedTuple):
    """The turn `plan` chose: found, axis (3,), angle, pivot (3,), the hand's raise, the joints (7,) at its end, and
    whether it fits the task: the put-down after it (if any) can be made, the object ends less than MAX_LIFT above
    where it was (the AT goal after an air turn allows 0.08 m), and, turned about the TCP, the arm can carry it back
    to where it was."""
    found: jnp.ndarray
    axis: jnp.ndarray
    angle: jnp.ndarray
    pivot: jnp.ndarray
    raise_by: jnp.ndarray
    joints: jnp.ndarray
    fits: jnp.ndarray


def plan(kinematics, q, hand_pos, hand_quat, object_pos, object_points, object_valid, v, d, on_table,
         settle=False) -> TurnPlan:
    """The turn to make (TurnPlan) for one environment.

    q: the arm's joint targets now; hand_pos/hand_quat: the commanded TCP pose the turn starts from; object_points
    (M, 3) world; v: the part's direction now (unnormalised is fine); d: the goal direction; on_table: yaw only;
    settle: a put-down follows the turn, so options after which it cannot be made rank last.
    """
    axes, angles, valid = options(v, d, on_table)
    middle = jnp.where(on_table, pushing.footprint_centre(object_points, object_valid), object_pos)
    pivots = jnp.concatenate([jnp.tile(middle, (NUM_TWISTS, 1)), jnp.tile(hand_pos, (NUM_TWISTS, 1))])

    def evaluate(axis, angle, pivot, about_tcp):
        def lowest(fraction, centre=pivot):
            turn = axis_angle_to_quat(axis, fraction * angle)
            moved = centre + quat_rotate(turn, object_points - centre)
            return jnp.where(object_valid, moved[:, 2], jnp.inf).min()

        def clearance_raise(fractions, centre=pivot):
            # How far the hand must rise to keep the object and the hand TABLE_CLEARANCE above the table at these
            # fractions of the turn about `centre`.
            low = jnp.stack([jnp.minimum(lowest(f, centre),
                                         hand_bottom(*turned_pose(centre, axis, angle, f, hand_pos, hand_quat)))
                             for f in fractions]).min()
            return jnp.maximum(0.0, TABLE_HEIGHT + TABLE_CLEARANCE - low)

        raise_by = jnp.where(on_table, 0.0, clearance_raise((0.5, 1.0)))

        def follow(carry, fraction):
            pos, quat = turned_pose(pivot, axis, angle, fraction, hand_pos, hand_quat)
            pos = pos + raise_by * jnp.asarray(UP) * jnp.minimum(1.0, 2 * fraction)
            return _reach_step(kinematics, *carry, pos, quat), None

        (joints, ok), _ = jax.lax.scan(follow, (q, jnp.asarray(True)), jnp.asarray(FRACTIONS, jnp.float32))
        turned_origin = pivot + quat_rotate(axis_angle_to_quat(axis, angle), object_pos - pivot)
        # The hand's pose at the turn's end, raised.
        end_pos, end_quat = turned_pose(pivot, axis, angle, 1.0, hand_pos, hand_quat)
        end_pos = end_pos + raise_by * jnp.asarray(UP)

        def put_down():
            # The hand lowers the object until its lowest point meets the table or the hand meets it first, and the
            # arm must reach the way down. AT after the put-down measures the object's origin from where it rested
            # before the lift: the origin must end near the height above the table it rested at (a bucket turned
            # upside down by its rim stays a few centimetres up, held where the hand meets the table: the task's AT
            # still holds, the put-down skill's ON does not).
            drop = jnp.maximum(lowest(1.0) + raise_by - TABLE_HEIGHT, 0.0)
            hand_room = hand_bottom(end_pos, end_quat) - TABLE_HEIGHT + PUT_DOWN_SLACK
            descent = jnp.clip(jnp.minimum(drop, hand_room), 0.0, None)

            def lower(carry, fraction):
                return _reach_step(kinematics, *carry, end_pos - fraction * descent * jnp.asarray(UP), end_quat), None

            (_, down_ok), _ = jax.lax.scan(lower, (joints, jnp.asarray(True)), jnp.asarray(PUT_DOWN_FRACTIONS))
            rested_at = object_pos[2] - lowest(0.0)
            ends_at = turned_origin[2] + raise_by - descent - TABLE_HEIGHT
            # Whether it can be made, and whether it ends with the object held above the table.
            return down_ok & (jnp.abs(ends_at - rested_at) < MAX_RESTING_CHANGE), descent < drop

        def carried_back(lift):
            # The arm must reach the hand's pose with the turned object's origin back in its place (the object turned
            # about its origin, raised by `lift`), along the way from the turn's end.
            back_pos, _ = turned_pose(object_pos, axis, angle, 1.0, hand_pos, hand_quat)
            back_pos = back_pos + lift * jnp.asarray(UP)

            def carry(state, fraction):
                return _reach_step(kinematics, *state, end_pos + fraction * (back_pos - end_pos), end_quat), None

            (_, reached), _ = jax.lax.scan(carry, (joints, jnp.asarray(True)), jnp.asarray(CARRY_BACK_FRACTIONS))
            return reached

        # Only a turn with a put-down after it pays for the check (a real branch where `settle` is not batched).
        settled, held = jax.lax.cond(settle, put_down, lambda: (jnp.asarray(True), jnp.asarray(False)))
        displacement = jnp.linalg.norm(turned_origin - object_pos) + raise_by
        cost = (angle + 4.0 * displacement + 20.0 * jnp.maximum(displacement - MAX_DISPLACEMENT, 0.0)
                + 3.0 * raise_by + jnp.where(settled, jnp.where(held, HELD_COST, 0.0), UNSETTLED_COST))
        # How far above where it was the object ends: raised with the hand about its origin, or, turned about the
        # TCP and carried back, as high as the turned hand and object must be with the origin back in its place.
        lift = jnp.where(on_table, 0.0, jnp.where(about_tcp, clearance_raise((1.0,), object_pos), raise_by))
        fits = settled & (lift < MAX_LIFT) & jax.lax.cond(
            about_tcp & ~on_table & (jnp.linalg.norm(turned_origin - object_pos) > CARRY_BACK_START),
            lambda: carried_back(lift), lambda: jnp.asarray(True))
        return ok, cost + jnp.where(fits, 0.0, UNFIT_COST), raise_by, joints, fits

    about_tcp = jnp.arange(2 * NUM_TWISTS) >= NUM_TWISTS
    ok, cost, raise_by, joints, fits = jax.vmap(evaluate)(axes, angles, pivots, about_tcp)
    ok = ok & valid
    best = jnp.argmin(jnp.where(ok, cost, jnp.inf))
    return TurnPlan(ok.any(), axes[best], angles[best], pivots[best], raise_by[best], joints[best], fits[best])
