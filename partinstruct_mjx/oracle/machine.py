"""The scripted expert as a batched JAX state machine: each environment walks its skill chain in stages.

Every step `act` turns the observed SceneState into one 7-D pose action per environment by moving a commanded TCP
pose (speed-limited) towards the current stage's goal; stages advance on arrival, on the skill's effects (spec 5.2,
evaluated like the original's OracleChecker with p0 = the object position when the oracle started the skill) or
when their step budget runs out. Grasp and touch poses come from `plan` (candidates.py plus an IK reach check),
which the driver calls only on the steps where some environment asks for it. Budgets are step counts.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from partinstruct_mjx.control import jax_ik
from partinstruct_mjx.control.rotations import (axis_angle_to_quat, quat_error, quat_multiply, quat_rotate,
                                                quat_to_euler_xyz)
from partinstruct_mjx.oracle import candidates, lookahead, pushing, rotation
from partinstruct_mjx.oracle.kinds import GRASP, MOVE, RELEASE, ROTATE, SKILL_KINDS, TOUCH
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import TABLE_HEIGHT
from partinstruct_mjx.sim.state import unpacked
from partinstruct_mjx.tasks import predicates, progress
from partinstruct_mjx.tasks.part_geometry import PartGeometry, PartNames, spatial_masks
from partinstruct_mjx.tasks.vocabulary import OPPOSITE, UNIT_DISTANCE, direction_vector

DONE = -1
"""Skill value once the whole chain is executed."""

SKILL_BUDGET = np.array([200, 160, 150, 110, 70])
"""Steps one skill may take (grasp and touch include their retries), by kind."""
MAX_ATTEMPTS = 3
"""Grasp/touch candidates tried (in rank order) before the skill fails."""

FREE_SPEED = 0.02
APPROACH_SPEED = 0.007
CARRY_SPEED = 0.01
PUSH_SPEED = 0.006
TURN_SPEED = 0.12
PLANNED_TURN_SPEED = 0.08
"""Commanded TCP speed limits per 20 Hz step (metres, radians)."""
ARRIVED = 0.012
"""Measured TCP distance to a waypoint that counts as arrived (the servos lag the command)."""
VIA_HEIGHT = 0.06
"""Waypoints before a pregrasp/pretouch pose are raised this much, so the hand comes from above."""
CLOSE_STEPS = 14
"""Steps the fingers get to close (0.25 s filter) before the grasp is judged."""
GRIP_SETTLED = 0.0005
"""A grasp counts once GRASPING holds and the fingers moved less than this (m) in the last step: an object that
squeezes out of closing fingers is caught at the grasp (and retried), not during the carry."""
MOVE_TOLERANCE = 0.012
"""The oracle's own move ends within this of p0 + 0.12 dir (the effect allows 0.05)."""
ROTATE_TOLERANCE = 0.2
"""Radians between the part's direction and the goal at which a rotation ends (FACING allows 0.5)."""
RETREAT_BACK = 0.05
RETREAT_UP = 0.10
"""Release: back off along the TCP's z, then up (spec 8.8, the oracle config's 0.1 m)."""
FINGER_OPENED = 0.035
"""Release: finger opening (m) at which the hand starts backing off."""
LOST_STEPS = 6
"""Steps a carry, push or turn may go on without holding (or touching) the object before the skill fails."""
PUSH_TILTS = (0.35, 0.7, 1.05, 1.4)
"""Pushes press with the hand tilted down by the first of these (rad) the arm reaches with the hand above the table:
the flatter the hand, the closer TOUCHING's fingertip point (the pads' far end) is to what the pads press."""
PUSH_BACK_OFF = 0.04
TOUCH_PRESS = 0.01
"""Metres the fingertip leaves the object before re-approaching it low, and how far past the face it aims."""
DETOUR_DISTANCE = 0.06
DETOUR_CLEARANCE = 0.03
"""A push whose pre-push pose lies farther than this (m, horizontally) from where the touch before it ended goes
round above the object, with the fingertip this much above the object's top."""
PUSH_START_TOLERANCE = 0.015
"""A touch that ends this close (m) to where the push starts pushes from there."""
PUSH_STEER = 0.15
PUSH_STEER_LIMIT = 0.002
"""Share of the fingertip's sideways offset from the line through the object's middle corrected per step, and the
most (m) corrected per step (sliding the fingertip fast along the object drags it sideways)."""
RIDE_OVER = 0.015
"""A fingertip this far (m) past the push point along the push, out of touch, has ridden over the object (a knife,
a flat box): it goes back round above the object (up, back at height, down behind it) instead of straight back,
which would drag the object the wrong way."""
PUSH_APPROACH_STEPS = 30
PUSH_APPROACH_NEAR = 0.03
"""A push's approach that has not touched the object after this many steps, with the fingertip this close (m) to
the push point, pushes from there (`push_approached`)."""
PUSH_SLIP_STEPS = 2
"""Steps a push goes on without touching before the fingertip approaches the push point again."""
PUSH_ADVANCING = 0.001
"""Metres the object went along a push since the previous step that count as the robot pushing it."""
PUSH_LOOKAHEAD = 0.04
PUSH_STOP = 0.006
"""A push heads for the point this far ahead of the object on its line (m), and stops this short of the goal."""
RETOUCH_BACK = 0.02
"""Metres behind the touched part the fingertip waits before touching it again after a push."""
RIM_ABOVE = 0.004
RIM_OVER = 0.003
"""Touching again after a push aims the fingertip this far (m) above the top of the touched part's rear face and this
far past its rear edge (TOUCHING holds within 1 cm). Pressing the face itself, the pads' edge met it first and
stopped the fingertip, the middle of the pads' end, 1-1.4 cm away."""
TURN_START_SPEED = 0.01
TURN_ACCELERATION = 0.004
"""A turn's speed starts at this (rad per step) and grows by this per step up to its limit (PLANNED_TURN_SPEED in
18 steps), as carries do. Kept with the grasps' lever term and the turn's end (docs/oracle.md: 381 -> 390 of 435
episodes together, 387 with the lever term alone); a contact trace of a dropped scissors turn found no twist in
the pads before the drop, so the ramp is not known to fix that cause."""
TOUCH_TIPPING = 0.1
"""Radians a touch's approach may tilt the object before it backs off and takes the next candidate: the pads met a
tall, light object (a display) before the fingertip reached the part, and pushing on tipped it over."""
RECENTRE_START = rotation.CARRY_BACK_START
RECENTRE_DONE = 0.015
RECENTRE_STEPS = 40
RECENTRE_ACCELERATION = 0.001
"""A turn that leaves the object origin more than RECENTRE_START (m) from where the rotation started (a turn about
the TCP swings it round the grasp) carries it back, holding the part on its goal, until within RECENTRE_DONE or
after RECENTRE_STEPS; the carry's speed grows by RECENTRE_ACCELERATION per step up to CARRY_SPEED. The task's AT
goals (0.05-0.08 m) judge the object where the moves before the turn put it."""
SETTLE_GAP = 0.001
SETTLE_SPEED = 0.002
"""Where the task's current goals include ON, a turn on the table or a carry of the object held on it (a slide)
lowers the hand, by at most SETTLE_SPEED (m) per step, while the object's lowest point is more than SETTLE_GAP
above the table, and ends only with the object on it: a dispenser turned on the table rose 1.4 cm in the pads and
a kitchen pot 4 mm in its slide, and ON (2 mm) never held."""
AIR_TURN_LEVER_WEIGHT = 20.0
"""Grasp score lost per metre between the object's middle and the pinch axis in chains that turn the object in the
air (candidates.grasp_candidates' lever_weight)."""
LIFT_START_SPEED = 0.0015
LIFT_ACCELERATION = 0.000125
"""A carry's commanded speed starts at this (m per step) and grows by this per step up to CARRY_SPEED (68 steps;
a 0.12 m carry is commanded over about 33 steps, 26 at twice the rate): the grip takes the object's weight gently.
Twice this acceleration lost 8-12 of 880 episodes, mostly objects slipping out in carries; four times it another
8-9 (docs/oracle.md)."""


@struct.dataclass
class OracleState:
    """Per-environment machine state (batch first). Chain fields are fixed per episode."""

    kind: jnp.ndarray          # (B, S) skill kinds
    part: jnp.ndarray          # (B, S) part rows (-1 none)
    direction: jnp.ndarray     # (B, S, 3)
    grasping: jnp.ndarray      # (B, S) move flags
    touching: jnp.ndarray
    put_down: jnp.ndarray
    push_side: jnp.ndarray     # (B, S, 3) touch: the side a following push needs
    on_table_turn: jnp.ndarray  # (B, S) rotation of an object kept on the table (yaw only)
    num_skills: jnp.ndarray    # (B,)
    skill: jnp.ndarray         # (B,) executing skill, DONE at the end
    stage: jnp.ndarray
    stage_steps: jnp.ndarray
    skill_steps: jnp.ndarray
    attempt: jnp.ndarray
    skip: jnp.ndarray          # (B,) best candidates a backtracking try passes over (backtrack.with_try)
    lost: jnp.ndarray          # (B,) consecutive steps without the grasp/touch a skill needs
    needs_plan: jnp.ndarray
    failed: jnp.ndarray
    failed_skill: jnp.ndarray  # (B,) index of the skill that failed, -1
    p0: jnp.ndarray            # (B, 3) object position when the skill started
    masks: jnp.ndarray         # (B, 7, M) spatial parts sampled when the skill started
    cmd_pos: jnp.ndarray
    cmd_quat: jnp.ndarray
    finger: jnp.ndarray
    grip_width: jnp.ndarray   # (B,) finger opening measured at the previous step
    target_pos: jnp.ndarray   # grasp/touch TCP pose from the planner
    target_quat: jnp.ndarray
    target_open: jnp.ndarray  # (B,) finger opening a grasp approaches with (pre-shaped to the section it pinches)
    approach: jnp.ndarray     # (B, 3) unit axis the TCP moves along into the target
    turn_axis: jnp.ndarray    # (B, 3) rotate: the planned turn (rotation.py), about turn_pivot
    turn_angle: jnp.ndarray
    turn_pivot: jnp.ndarray
    turn_raise: jnp.ndarray   # (B,) metres the hand rises during the turn (keeps the object above the table)
    anchor_pos: jnp.ndarray   # (B, 3) commanded TCP pose when a turn or a push was planned (it starts from there),
    #                           in a turn's carry back the TCP's goal
    anchor_quat: jnp.ndarray
    turn_progress: jnp.ndarray  # (B,) fraction of the planned turn commanded so far
    last_object: jnp.ndarray   # (B, 3) object position at the previous step
    approach_up: jnp.ndarray   # (B, 3) the world's up axis in the object's frame when a touch's approach began
    key: jnp.ndarray


def compile_chains(episodes, names: PartNames) -> dict[str, np.ndarray]:
    """Host arrays of every episode's chain for `init`: kinds, part rows, directions, move flags, push sides."""
    batch, size = len(episodes), progress.MAX_SKILLS
    out = {"kind": np.full((batch, size), RELEASE, np.int32), "part": np.full((batch, size), -1, np.int32),
           "direction": np.zeros((batch, size, 3), np.float32), "grasping": np.zeros((batch, size), bool),
           "touching": np.zeros((batch, size), bool), "put_down": np.zeros((batch, size), bool),
           "push_side": np.zeros((batch, size, 3), np.float32), "on_table_turn": np.zeros((batch, size), bool),
           "num_skills": np.array([len(e.chain) for e in episodes], np.int32)}
    for b, episode in enumerate(episodes):
        lifted = False
        for s, step in enumerate(episode.chain):
            out["kind"][b, s] = SKILL_KINDS[step.name]
            if step.part is not None:
                out["part"][b, s] = names.index(step.part)
            if step.direction is not None:
                out["direction"][b, s] = direction_vector(step.direction)
            out["grasping"][b, s], out["touching"][b, s], out["put_down"][b, s] = (step.grasping, step.touching,
                                                                                  step.put_down)
            nxt = episode.chain[s + 1] if s + 1 < len(episode.chain) else None
            if step.name == "touch_obj" and nxt is not None and nxt.name == "move_gripper" and nxt.touching:
                out["push_side"][b, s] = direction_vector(OPPOSITE[nxt.direction])
            if step.name == "move_gripper" and step.direction in ("top", "bottom"):
                lifted = step.direction == "top"
            if step.name == "grasp_obj":
                lifted = False
            out["on_table_turn"][b, s] = step.name == "rotate_obj" and not lifted
    return out


def init(chains: dict, data, geometry: PartGeometry, keys: jax.Array) -> OracleState:
    """Machine state at reset: first skill, command = the current TCP pose, fingers as they are; keys (B, 2), one
    per episode, so an episode's demo does not depend on its batch."""
    batch = chains["kind"].shape[0]
    masks = _sampled_masks(data, geometry)
    fields = {k: jnp.asarray(v) for k, v in chains.items()}
    zeros = jnp.zeros(batch, jnp.int32)
    return OracleState(
        **fields, skill=zeros, stage=zeros, stage_steps=zeros, skill_steps=zeros, attempt=zeros, skip=zeros, lost=zeros,
        needs_plan=fields["kind"][:, 0] <= TOUCH, failed=jnp.zeros(batch, bool),
        failed_skill=jnp.full(batch, -1, jnp.int32), p0=jnp.asarray(data.object_pos, jnp.float32), masks=masks,
        cmd_pos=jnp.asarray(data.tcp_pos, jnp.float32), cmd_quat=jnp.asarray(data.tcp_quat, jnp.float32),
        finger=jnp.asarray(data.finger_qpos[:, 0], jnp.float32),
        grip_width=jnp.asarray(data.finger_qpos[:, 0], jnp.float32),
        target_pos=jnp.asarray(data.tcp_pos, jnp.float32), target_quat=jnp.asarray(data.tcp_quat, jnp.float32),
        target_open=jnp.full(batch, panda.FINGER_OPEN, jnp.float32), approach=jnp.zeros((batch, 3), jnp.float32),
        turn_axis=jnp.zeros((batch, 3), jnp.float32).at[:, 2].set(1.0),
        turn_angle=jnp.zeros(batch, jnp.float32), turn_pivot=jnp.zeros((batch, 3), jnp.float32),
        turn_raise=jnp.zeros(batch, jnp.float32), anchor_pos=jnp.asarray(data.tcp_pos, jnp.float32),
        anchor_quat=jnp.asarray(data.tcp_quat, jnp.float32), turn_progress=jnp.zeros(batch, jnp.float32),
        last_object=jnp.asarray(data.object_pos, jnp.float32),
        approach_up=jax.vmap(object_up)(jnp.asarray(data.object_quat, jnp.float32)), key=jnp.asarray(keys))


# --- planning -----------------------------------------------------------------------------------------------


def plan(oracle: OracleState, data, geometry: PartGeometry, kinematics, joint_targets) -> OracleState:
    """Plan for every environment that asks (`needs_plan`): the grasp or touch pose at the start of those skills
    (the (`attempt` + `skip`)-th reachable candidate in rank order; an empty sample is drawn again on the next step
    until MAX_ATTEMPTS, then the skill fails), the turn at the start of a rotation (rotation.py). The others pass
    through; each kind is computed only when some environment needs it. `data` is a SceneState or its `for_jit()`."""
    data = unpacked(data)
    index = jnp.clip(oracle.skill, 0, progress.MAX_SKILLS - 1)[:, None]
    kind = jnp.take_along_axis(oracle.kind, index, axis=1)[:, 0]
    push = (kind == MOVE) & jnp.take_along_axis(oracle.touching, index, axis=1)[:, 0]
    for planner, needed in ((_plan_grasp, kind == GRASP), (_plan_touch, kind == TOUCH), (_plan_turn, kind == ROTATE),
                            (_plan_push, push)):
        oracle = jax.lax.cond((oracle.needs_plan & needed).any(),
                              partial(_per_scene, planner, data=data, geometry=geometry, kinematics=kinematics,
                                      joint_targets=joint_targets), lambda o: o, oracle)
    return oracle


def _per_scene(planner, oracle: OracleState, data, geometry: PartGeometry, kinematics, joint_targets) -> OracleState:
    """`planner` for every scene of the batch. A batch of one (a scene planned alone) is planned without vmap: XLA
    compiles the vmapped grasp planner into a program twice as slow on a CPU (107 against 54 ms)."""
    if oracle.skill.shape[0] == 1:
        first = partial(jax.tree.map, lambda x: x[0])
        planned = planner(first(oracle), first(data), geometry, kinematics, joint_targets[0])
        return jax.tree.map(lambda x: x[None], planned)
    return jax.vmap(planner, in_axes=(0, 0, None, None, 0))(oracle, data, geometry, kinematics, joint_targets)


def _plan_push(o: OracleState, data, geo: PartGeometry, kinematics, q):
    """Where a push starts: the fingertip at the push point of the touched part (pushing.py), with the first hand
    tilt (PUSH_TILTS) that keeps the hand above the table and at which the arm reaches the pre-push pose, the start
    and the end of the push."""
    index = jnp.clip(o.skill, 0, progress.MAX_SKILLS - 1)
    need = o.needs_plan & (o.kind[index] == MOVE) & o.touching[index]
    direction = o.direction[index]
    touched_part = jnp.maximum(o.part[jnp.maximum(index - 1, 0)], 0)
    touched, touched_valid = predicates.part_cloud(data, geo, o.masks, touched_part)
    point, _ = pushing.push_point(touched, touched_valid, predicates.object_points(data, geo), geo.valid[geo.whole],
                                  direction)
    poses = [_push_pose(point, direction, tilt) for tilt in PUSH_TILTS]
    # The palm (a capsule 2 cm behind the TCP, 2.8 cm thick) and the pads' lower edge stay above the table.
    clear = [(pos[2] - 0.02 * jnp.sin(tilt) - candidates.HAND_RADIUS > TABLE_HEIGHT + 0.005)
             & (point[2] - candidates.PAD_HALF_WIDTH * jnp.cos(tilt) > TABLE_HEIGHT + 0.002)
             for (pos, _), tilt in zip(poses, PUSH_TILTS)]
    reached = [ok & lookahead.reach_all(kinematics, q, jnp.stack([pos - PUSH_BACK_OFF * direction, pos,
                                                                  pos + UNIT_DISTANCE * direction]), quat)[0]
               for (pos, quat), ok in zip(poses, clear)]
    pick = jnp.argmax(jnp.stack(reached + [jnp.asarray(True)]))
    pos = jnp.stack([p for p, _ in poses] + [poses[-1][0]])[pick]
    quat = jnp.stack([r for _, r in poses] + [poses[-1][1]])[pick]
    return o.replace(target_pos=jnp.where(need, pos, o.target_pos), target_quat=jnp.where(need, quat, o.target_quat),
                     anchor_pos=jnp.where(need, o.cmd_pos, o.anchor_pos), needs_plan=o.needs_plan & ~need)


def _plan_turn(o: OracleState, data, geo: PartGeometry, kinematics, q):
    index = jnp.clip(o.skill, 0, progress.MAX_SKILLS - 1)
    need = o.needs_plan & (o.kind[index] == ROTATE)
    flat = o.on_table_turn[index]
    vector = predicates.part_vector(data, geo, o.masks, jnp.maximum(o.part[index], 0))
    vector = jnp.where(flat, vector * jnp.array([1.0, 1.0, 0.0]), vector)
    following = jnp.clip(index + 1, 0, progress.MAX_SKILLS - 1)
    settle = (index + 1 < o.num_skills) & (o.kind[following] == MOVE) & o.put_down[following]
    found, axis, angle, pivot, raise_by, *_ = rotation.plan(
        kinematics, q, o.cmd_pos, o.cmd_quat, data.object_pos, *_object_cloud(data, geo), vector, o.direction[index],
        flat, settle)
    take = need & found
    return o.replace(
        turn_axis=jnp.where(take, axis, o.turn_axis), turn_angle=jnp.where(take, angle, o.turn_angle),
        turn_pivot=jnp.where(take, pivot, o.turn_pivot), turn_raise=jnp.where(take, raise_by, o.turn_raise),
        anchor_pos=jnp.where(need, o.cmd_pos, o.anchor_pos),
        anchor_quat=jnp.where(need, o.cmd_quat, o.anchor_quat),
        turn_progress=jnp.where(need, 0.0, o.turn_progress),
        # Without a plan the closed-loop correction (stage 2) turns the hand the shortest way.
        stage=jnp.where(need, jnp.where(found, 1, 2), o.stage), stage_steps=jnp.where(need, 0, o.stage_steps),
        needs_plan=o.needs_plan & ~need)


def _plan_grasp(o: OracleState, data, geo: PartGeometry, kinematics, q):
    index = jnp.clip(o.skill, 0, progress.MAX_SKILLS - 1)
    part = jnp.maximum(o.part[index], 0)
    key, sub = jax.random.split(o.key)
    object_points, object_valid = _object_cloud(data, geo)
    object_normals = quat_rotate(data.body_quat[geo.bodies[geo.whole][::2]], geo.normals[geo.whole][::2])
    part_points, part_valid = predicates.part_cloud(data, geo, o.masks, part)
    part_normals = quat_rotate(data.body_quat[geo.bodies[part]], geo.normals[part])
    # A chain that turns the object on the table later needs the hand above it (a turned side grasp points the
    # hand back at the robot).
    later = jnp.arange(progress.MAX_SKILLS) > index
    table_turn = (later & (o.kind == ROTATE) & o.on_table_turn).any()
    # A turn in the air later tilts the object in the pads: grasp it near the line through its middle.
    air_turn = (later & (o.kind == ROTATE) & ~o.on_table_turn).any()
    grasps = candidates.grasp_candidates(object_points, object_normals, object_valid, part_points, part_normals,
                                          part_valid, sub, top_down_weight=jnp.where(
                                              table_turn, TABLE_TURN_TOP_DOWN_WEIGHT, candidates.TOP_DOWN_WEIGHT),
                                          lever_weight=jnp.where(air_turn, AIR_TURN_LEVER_WEIGHT, 0.0))
    top = candidate_pool(grasps["score"], jnp.abs(grasps["approach"][:, 2]) < LEVEL_APPROACH, air_turn)
    top_score = grasps["score"][top]
    approach, closing = grasps["approach"][top], grasps["closing"][top]
    # Both closing directions of each grasp (the hand turned half a turn about its axis), the one nearer the
    # current hand orientation first.
    position, quat_a, quat_b = jax.vmap(candidates.tcp_pose)(grasps["centre"][top], approach, closing)
    turn_a = jnp.linalg.norm(quat_error(quat_a, o.cmd_quat[None]), axis=-1)
    turn_b = jnp.linalg.norm(quat_error(quat_b, o.cmd_quat[None]), axis=-1)
    near = (turn_a <= turn_b)[:, None]
    quats = jnp.stack([jnp.where(near, quat_a, quat_b), jnp.where(near, quat_b, quat_a)], 1).reshape(-1, 4)
    approach = jnp.repeat(approach, 2, axis=0)
    positions = jnp.repeat(position, 2, axis=0)
    openings = jnp.repeat(grasps["opening"][top], 2)
    # Grasps after which the arm can carry out the rest of the chain (lookahead.py) come first.
    chain = {name: getattr(o, name) for name in ("kind", "direction", "put_down", "part", "on_table_turn",
                                                 "num_skills")}

    def part_vector(row):
        return predicates.part_vector(data, geo, o.masks, jnp.maximum(row, 0))

    def tier(i, joints):
        return lookahead.outlook(kinematics, joints, positions[i], quats[i], chain, index, data.object_pos,
                                 object_points, object_valid, part_vector)

    reachable, tiers = _rank_in_chunks(kinematics, q, positions, quats, approach,
                                       jnp.repeat(jnp.isfinite(top_score), 2), _top(object_points, object_valid),
                                       o.attempt + o.skip + 1, tier)
    return _take_candidate(o, key, o.kind[index] == GRASP, positions, quats, approach, openings, reachable, tiers)


def _first_tiers(reachable, tier_of, wanted):
    """(N,) outlook tiers (`tier_of(i)`, a costly test; lookahead.CLEAR_AND_FITS is best) of the reachable
    candidates in rank order until `wanted` of them are in the best tier (the rest: lookahead.BLOCKED): what
    `_take_candidate` needs to pick the same candidate as with every test run. Stops after the last reachable
    candidate."""
    end = jnp.max(jnp.where(reachable, jnp.arange(reachable.shape[0]) + 1, 0))

    def body(carry):
        i, best, tiers = carry
        t = jax.lax.cond(reachable[i], tier_of, lambda _: jnp.asarray(lookahead.BLOCKED), i)
        return i + 1, best + (t == lookahead.CLEAR_AND_FITS), tiers.at[i].set(t)

    def more(carry):
        i, best, _ = carry
        return (i < end) & (best < wanted)

    start = (0, 0, jnp.full(reachable.shape, lookahead.BLOCKED))
    return jax.lax.while_loop(more, body, start)[2]


def _plan_touch(o: OracleState, data, geo: PartGeometry, kinematics, q):
    index = jnp.clip(o.skill, 0, progress.MAX_SKILLS - 1)
    part = jnp.maximum(o.part[index], 0)
    key, _ = jax.random.split(o.key)
    object_points, object_valid = _object_cloud(data, geo)
    part_points, part_valid = predicates.part_cloud(data, geo, o.masks, part)
    touch_point, touch_axis, touch_x, touch_score = candidates.touch_candidates(
        object_points, object_valid, part_points, part_valid, o.push_side[index])
    order = jnp.argsort(-touch_score)
    axes = touch_axis[order]
    positions, quats = touch_poses(touch_point[order], axes, touch_x[order])
    reached, _ = jax.vmap(servo_reachable, in_axes=(None, None, 0, 0, 0, None))(kinematics, q, positions, quats, axes,
                                                                             _top(object_points, object_valid))
    reachable = jnp.isfinite(touch_score[order]) & reached
    closed = jnp.full(positions.shape[0], panda.FINGER_CLOSED)
    return _take_candidate(o, key, o.kind[index] == TOUCH, positions, quats, axes, closed, reachable,
                           jnp.zeros(positions.shape[0], int))


def touch_poses(points, axes, x_axes):
    """TCP positions and orientations (N, 3), (N, 4) that press the fingertip candidates.TOUCH_DEPTH into the
    surface at `points` along the TCP z axes `axes`, x axes `x_axes` (candidates.touch_candidates)."""
    return (points - (predicates.FINGERTIP_OFFSET - candidates.TOUCH_DEPTH) * axes,
            jax.vmap(candidates.touch_quat)(axes, x_axes))


def _top(points, valid):
    """Height of the highest valid point."""
    return jnp.where(valid, points[:, 2], -jnp.inf).max()


def _object_cloud(data, geo: PartGeometry):
    """Every other point of the object's cloud (world frame) and their validity: what the planners search."""
    return predicates.object_points(data, geo)[::2], geo.valid[geo.whole][::2]


def _take_candidate(o: OracleState, key, kind_matches, positions, quats, axes, openings, reachable,
                    tiers) -> OracleState:
    """Take the (`attempt` + `skip`)-th reachable candidate in rank order, lower `tiers` (a better outlook) first,
    as the grasp or touch pose; the last one when fewer are left. A retry's skip passes over the ones tried before,
    but no further than the best tier's last candidate (passing over a fresh sample's few grasps the look-ahead found
    clear took one it had found blocked).
    Nothing found: the candidates are a random sample (a thin part has few grasps), so draw again next step while
    attempts are left, then fail the skill."""
    order = jnp.argsort(tiers * positions.shape[0] + jnp.arange(positions.shape[0]))
    rank = jnp.cumsum(reachable[order]) - 1
    best_tier = jnp.where(reachable, tiers, lookahead.BLOCKED + 1).min()
    skip = jnp.minimum(o.skip, jnp.maximum((reachable & (tiers == best_tier)).sum() - 1, 0))
    chosen = reachable[order] & (rank == jnp.minimum(o.attempt + skip, reachable.sum() - 1))
    found = chosen.any()
    pick = order[jnp.argmax(chosen)]
    need = o.needs_plan & kind_matches
    empty = need & ~found
    fail = empty & (o.attempt + 1 >= MAX_ATTEMPTS)
    take = need & found
    return o.replace(
        target_pos=jnp.where(take, positions[pick], o.target_pos),
        target_quat=jnp.where(take, quats[pick], o.target_quat),
        approach=jnp.where(take, axes[pick], o.approach), target_open=jnp.where(take, openings[pick], o.target_open),
        stage=jnp.where(take, 1, o.stage), stage_steps=jnp.where(take, 0, o.stage_steps),
        attempt=o.attempt + (empty & ~fail), needs_plan=o.needs_plan & ~(take | fail), key=jnp.where(need, key, o.key),
        failed=o.failed | fail, failed_skill=jnp.where(fail & ~o.failed, o.skill, o.failed_skill))


REACH_CONFIG = jax_ik.IKConfig(iterations=40)
SERVO_STEPS = 48
SERVO_CONFIG = jax_ik.IKConfig(iterations=5)
"""`servo_reachable`'s steps of the command towards the via point, and its IK iterations per step (the env's IK
converges on a servo step in about 3)."""
TABLE_TURN_TOP_DOWN_WEIGHT = 2.0
"""candidates.TOP_DOWN_WEIGHT for grasps before a turn on the table."""
PLAN_CANDIDATES = 8
PLAN_CHUNKS = 3
"""Best-ranked grasps whose reach (with both closing directions) and outlook are checked with the IK, PLAN_CANDIDATES
at a time in rank order, the next ones only while fewer are in the outlook's best tier than the attempt needs, up to
PLAN_CHUNKS times: a laptop's front edge, to be held for a turn in the air (episode 4000216), had no reachable grasp
among the first 8 and the grasp failed at once; among the first 24 it had."""
LEVEL_APPROACH = 0.5
"""A grasp approaches level when its approach axis has a vertical component under this."""
LEVEL_BOOST = 100.0
"""Score added to level grasps to pick the last chunk of a chain with a turn in the air (more than any score)."""


def candidate_pool(score, level, air_turn):
    """Indices of the grasps whose reach and outlook are checked, in rank order: the PLAN_CANDIDATES * (PLAN_CHUNKS
    - 1) best, then, for a chain that turns the object in the air, the best `level` ones (a level approach lets the
    wrist roll the object over in place; held from above, an object turned upside down ends above the hand, too high
    for the AT goal after the turn), else the next best."""
    first = jax.lax.top_k(score, PLAN_CANDIDATES * (PLAN_CHUNKS - 1))[1]
    rest = score.at[first].set(-jnp.inf)
    boost = jnp.where(air_turn & level & jnp.isfinite(rest), LEVEL_BOOST, 0.0)
    return jnp.concatenate([first, jax.lax.top_k(rest + boost, PLAN_CANDIDATES)[1]])


def _rank_in_chunks(kinematics, q, positions, quats, axes, usable, object_top, wanted, tier_of):
    """(reachable (N,), tiers (N,)) of the candidate poses in rank order: checked with `servo_reachable` a chunk of
    2 * PLAN_CANDIDATES poses at a time, and the reachable ones with `tier_of(i, joints at the pose)` (the outlook,
    lazily: `_first_tiers`), until `wanted` are in the best tier (the chunks not checked: unreachable)."""
    size = 2 * PLAN_CANDIDATES

    def best(tiers):
        return (tiers == lookahead.CLEAR_AND_FITS).sum()

    def body(carry):
        i, reachable, tiers = carry
        chunk = [jax.lax.dynamic_slice_in_dim(x, i * size, size) for x in (positions, quats, axes, usable)]
        reached, solved = jax.vmap(servo_reachable, in_axes=(None, None, 0, 0, 0, None))(kinematics, q, *chunk[:3],
                                                                                        object_top)
        reached = reached & chunk[3]
        chunk_tiers = _first_tiers(reached, lambda j: tier_of(i * size + j, solved[j]), wanted - best(tiers))
        return (i + 1, jax.lax.dynamic_update_slice_in_dim(reachable, reached, i * size, 0),
                jax.lax.dynamic_update_slice_in_dim(tiers, chunk_tiers, i * size, 0))

    def more(carry):
        i, _, tiers = carry
        return (i * size < positions.shape[0]) & (best(tiers) < wanted)

    start = (0, jnp.zeros(positions.shape[0], bool), jnp.full(positions.shape[0], lookahead.BLOCKED))
    _, reachable, tiers = jax.lax.while_loop(more, body, start)
    return reachable, tiers


def approach_reachable(kinematics, q, position, quat, axis):
    """The IK reaches the via point, the pre-pose and the pose itself, each from the previous solution; and the
    joint angles at the pose."""
    pre, via = approach_waypoints(position, axis)
    return lookahead.reach_all(kinematics, q, jnp.stack([via, pre, position]), quat, REACH_CONFIG)


def approach_waypoints(position, axis):
    """The pre-pose PREGRASP_DISTANCE back along the approach `axis` from a grasp's or touch's TCP `position`, and
    the via point VIA_HEIGHT above it."""
    pre = position - candidates.PREGRASP_DISTANCE * axis
    return pre, pre + jnp.array([0.0, 0.0, VIA_HEIGHT])


def servo_reachable(kinematics, q, position, quat, axis, object_top):
    """`approach_reachable` as the servo gets there: SERVO_STEPS steps of the command from the hand's pose at `q`
    towards the via point (over the object first, `over_to`) at FREE_SPEED and TURN_SPEED, each solved from the
    step before with SERVO_CONFIG's iterations as the env's IK follows the command; then the pre-pose and the pose.
    Only those two must be reached (the machine moves on from a via point it does not reach).
    A solve straight to the via point can end on another branch of the arm's redundancy than the servo's path, which
    may pin joints on their limits on the way (kettle_007, test5 episode 5000076)."""
    pre, via = approach_waypoints(position, axis)

    def step(carry, _):
        cmd_pos, cmd_quat, joints = carry
        cmd_pos, cmd_quat = _toward(cmd_pos, cmd_quat, over_to(via, cmd_pos, object_top), quat, FREE_SPEED, TURN_SPEED)
        return (cmd_pos, cmd_quat, jax_ik._solve_one(kinematics, SERVO_CONFIG, joints, cmd_pos, cmd_quat)[0]), None

    (_, _, joints), _ = jax.lax.scan(step, (*jax_ik.forward_kinematics(kinematics, q), q), None, SERVO_STEPS)
    return lookahead.reach_all(kinematics, joints, jnp.stack([pre, position]), quat, REACH_CONFIG)


# --- acting -------------------------------------------------------------------------------------------------


def act(oracle: OracleState, data, task: progress.TaskState, geometry: PartGeometry, follow_env: bool = False
        ) -> tuple[OracleState, jnp.ndarray]:
    """One step of every environment's machine: the new state and the (B, 7) Euler pose actions.

    task: the env's progress; its skill effects (`skills`) are what the machine judges its skills by, and its spatial
    parts (`masks`) are the ones the env judges the task by, so the part a rotation turns or a push touches again is
    the env's. follow_env (an env in skill mode): the machine follows the env's skill chain (a skill ends when the env
    counts it, judged from the env's p0 and spatial parts) instead of its own tolerances. `data` is a SceneState or
    its `for_jit()`.
    """
    data = unpacked(data)
    follow = (task.skill_index, task.skill_p0, task.masks, task.task_p0)
    before = oracle.skill
    rows = progress.rows_at(task.skills, jnp.clip(oracle.skill, 0, progress.MAX_SKILLS - 1))
    # The spatial parts `_act_one` judges the skill with (the env's while it follows the env on the same skill).
    synced = follow_env & (task.skill_index == oracle.skill)
    facts = progress.goal_facts(data, geometry, jnp.where(synced[:, None, None], task.masks, oracle.masks), rows)
    phase_goals = progress.rows_at(task.phases, task.phase).kind
    oracle = jax.vmap(partial(_act_one, follow_env=follow_env), in_axes=(0, 0, None, 0, 0, 0, 0))(
        oracle, data, geometry, rows, facts, follow, phase_goals)
    oracle = oracle.replace(masks=_resampled_masks(oracle.skill != before, oracle.masks, data, geometry))
    euler = quat_to_euler_xyz(oracle.cmd_quat)
    return oracle, jnp.concatenate([oracle.cmd_pos, euler, oracle.finger[:, None]], axis=1)


def _toward(cmd_pos, cmd_quat, goal_pos, goal_quat, speed, turn):
    """The command moved towards a goal pose by at most `speed` metres and `turn` radians."""
    delta = goal_pos - cmd_pos
    distance = jnp.linalg.norm(delta)
    pos = cmd_pos + delta * jnp.minimum(1.0, speed / jnp.maximum(distance, 1e-9))
    rotation = quat_error(goal_quat, cmd_quat)
    angle = jnp.linalg.norm(rotation)
    step = jnp.minimum(angle, turn)
    quat = quat_multiply(axis_angle_to_quat(rotation / jnp.maximum(angle, 1e-9), step), cmd_quat)
    return pos, quat / jnp.linalg.norm(quat)


def _sampled_masks(data, geo: PartGeometry) -> jnp.ndarray:
    """(B, 7, M) spatial parts of every environment's object as it lies now."""
    return jax.vmap(lambda d: spatial_masks(predicates.object_points(d, geo)))(data)


def _resampled_masks(started, masks, data, geo: PartGeometry):
    """Spatial parts sampled afresh where a new skill `started` (computed only on steps where one did)."""
    def resample():
        return jnp.where(started.reshape((-1,) + (1,) * (masks.ndim - 1)), _sampled_masks(data, geo), masks)

    return jax.lax.cond(started.any(), resample, lambda: masks)


def _push_pose(point, direction, tilt):
    """TCP pose (position, quaternion) that puts the fingertip on `point` with the hand facing the push, tilted down
    by `tilt`."""
    z_axis = jnp.cos(tilt) * direction - jnp.sin(tilt) * jnp.array([0.0, 0.0, 1.0])
    pos = point - predicates.FINGERTIP_OFFSET * z_axis
    return pos.astype(jnp.float32), candidates.touch_quat(z_axis).astype(jnp.float32)


def over_to(via, tcp, object_top):
    """The goal on the way to a grasp's or touch's via point: first above it, with the TCP FINGERTIP_OFFSET +
    DETOUR_CLEARANCE over the object's top (straight up first from a TCP less than FINGERTIP_OFFSET above the top,
    where the fingers may reach down beside it), then down to it once the TCP is over it. A straight line to a via
    point on the far side of a tall object swept the hand through it (a display knocked over on the way to its
    front), and so did a line rising across it from a low start (a display's touch backing off from one side and
    going to the other)."""
    clear = object_top + predicates.FINGERTIP_OFFSET + DETOUR_CLEARANCE
    over = via.at[2].set(jnp.maximum(via[2], clear))
    rise = tcp.at[2].set(over[2])
    far = jnp.linalg.norm((tcp - via)[:2]) > ARRIVED
    low = tcp[2] < object_top + predicates.FINGERTIP_OFFSET
    return jnp.where(far, jnp.where(low, rise, over), via)


def over_and_back(goal, cmd_pos, tip, push_point, direction, z_axis, object_top, in_contact):
    """The approach goal of a push (`goal`), or, for a fingertip out of touch that rode over the object (more than
    RIDE_OVER past the push point along `direction`) or is on its way back above it, the next waypoint round above
    it: straight up until the fingertip clears the top by DETOUR_CLEARANCE, back at that height until it is
    PUSH_BACK_OFF behind the push point, then down."""
    clear = object_top + DETOUR_CLEARANCE
    tip_to_tcp = -predicates.FINGERTIP_OFFSET * z_axis
    behind = push_point - PUSH_BACK_OFF * direction
    along = (tip - push_point) @ direction
    past = along > RIDE_OVER
    high = tip[2] > object_top + DETOUR_CLEARANCE / 2
    lift = cmd_pos.at[2].add(clear - tip[2])
    back = jnp.where(along > -PUSH_BACK_OFF / 2, behind.at[2].set(clear), behind) + tip_to_tcp
    return jnp.where(~in_contact & (past | high), jnp.where(past & ~high, lift, back), goal)


def push_approach(anchor, z_axis, pre_push, cmd_pos, object_top):
    """Waypoints from where the touch before a push ended (`anchor`, the hand's axis `z_axis`) to the pre-push pose:
    the back-off goal, the current goal towards the pre-push pose, and whether the hand is still crossing over.

    The hand backs off along its own axis and up. After a touch elsewhere (another side of the object, more than
    DETOUR_DISTANCE away) it goes round above the object: up until the fingertip is DETOUR_CLEARANCE above the
    object's top, across, then down to the pre-push pose (a straight line would sweep the fingers through it).
    """
    up = jnp.array([0.0, 0.0, 1.0])
    flat = jnp.array([1.0, 1.0, 0.0])
    over = object_top + predicates.FINGERTIP_OFFSET + DETOUR_CLEARANCE
    back_off = anchor - PUSH_BACK_OFF * z_axis + PUSH_BACK_OFF * up
    detour = jnp.linalg.norm((anchor - pre_push) * flat) > DETOUR_DISTANCE
    crossing = detour & (jnp.linalg.norm((cmd_pos - pre_push) * flat) > ARRIVED / 2)
    back_off = jnp.where(detour, back_off.at[2].set(jnp.maximum(back_off[2], over)), back_off)
    return back_off, jnp.where(crossing, pre_push.at[2].set(over), pre_push), crossing


def rim_point(points, valid, direction, tip):
    """Where touching a part again after a push along `direction` aims the fingertip (before RIM_OVER): RIM_ABOVE
    above the top of the part's rear face (the face towards the pusher), the top point nearest `tip` sideways."""
    rear = pushing.face(points, valid, -direction)
    offset = points - tip
    sideways = (offset - (offset @ direction)[:, None] * direction) * jnp.array([1.0, 1.0, 0.0])
    top = jnp.argmax(jnp.where(rear, points[:, 2] - 0.5 * jnp.linalg.norm(sideways, axis=-1), -jnp.inf))
    return points[top] + jnp.array([0.0, 0.0, RIM_ABOVE])


def object_up(object_quat):
    """The world's up axis in the frame of an object at orientation `object_quat` (its tilt, whatever its yaw)."""
    inverse = object_quat * jnp.array([1.0, -1.0, -1.0, -1.0])
    return quat_rotate(inverse, jnp.array([0.0, 0.0, 1.0]))


def tipped(up_now, up_before):
    """Whether the object tilted more than TOUCH_TIPPING between two of its `object_up` axes."""
    return up_now @ up_before < jnp.cos(TOUCH_TIPPING)


def reach_counted(effects, is_touch, stage, grip_width, previous_width):
    """A touch is judged as it approaches: done the moment its effects hold (from the pre-pose on). A grasp is done
    once its effects hold after the fingers closed (stage 4 on) and stopped moving (less than GRIP_SETTLED since the
    previous step), so an object squeezing out of closing fingers is caught at the grasp, not during the carry."""
    settled = jnp.abs(grip_width - previous_width) < GRIP_SETTLED
    return effects & jnp.where(is_touch, stage >= 2, (stage >= 4) & settled)


def push_approached(in_contact, steps, tip, push_point, pushed_enough):
    """A push's approach (stage 2) ends when the fingers touch the object, when the object already went far enough
    (the hand, not the fingers, pushed it: a laptop's screen leaning over the push point), or after
    PUSH_APPROACH_STEPS with the fingertip within PUSH_APPROACH_NEAR of the push point. A fingertip still going
    round above the object (it rode over it, `over_and_back`) goes on: pushing from up there knocked a display over."""
    near = jnp.linalg.norm(tip - push_point) < PUSH_APPROACH_NEAR
    return in_contact | pushed_enough | ((steps > PUSH_APPROACH_STEPS) & near)


def push_counted(effects, touching_part, stage, pushed_enough):
    """A push is done when its effects hold and the touched part is under the fingertip, once the object went far
    enough: in stage 3 as it goes, in stages 4-5 (which come after) even if it sprang back a little as the hand let
    go (the effects allow 5 cm; waiting for the distance again ran the push out of its budget)."""
    return effects & touching_part & ((stage >= 4) | ((stage == 3) & pushed_enough))


def starting_p0(kinds, index, object_pos, task_p0, follow_env: bool):
    """The p0 (3,) the skill at `index` of the chain `kinds` (S,) starts with: where the object is now, except in task
    mode for the chain's first move after grasps and touches only, which is measured from where the object was when
    the task started (`task_p0`), as the task's AT goal is: a grasp or touch that missed may have pushed it aside
    (laptop_001, 880 draw, episode 367: 6 cm, and the push that followed went 12 cm from there)."""
    if follow_env:
        return object_pos
    earlier = jnp.arange(kinds.shape[0]) < index
    from_start = (kinds[index] == MOVE) & ~(earlier & (kinds > TOUCH)).any()
    return jnp.where(from_start, task_p0, object_pos)


def _act_one(o: OracleState, data, geo: PartGeometry, rows, facts, env, phase_goals, follow_env: bool):
    """One environment's step. phase_goals: the kinds of the goals of the env's current task phase."""
    env_skill, env_p0, env_masks, task_p0 = env
    keep_on = (phase_goals == progress.GOAL_KINDS.index("ON")).any()
    # In task mode a push touches its part again (stages 4-5) only for a task goal that names it still to come.
    retouch = follow_env | (phase_goals == progress.GOAL_KINDS.index("TOUCHING")).any()
    if follow_env:
        # While the machine is on the env's skill it judges it as the env does; once the env has counted a skill the
        # machine still finishes it (see below) with the p0 it had.
        synced = env_skill == o.skill
        o = o.replace(p0=jnp.where(synced, env_p0, o.p0), masks=jnp.where(synced, env_masks, o.masks))
    index = jnp.clip(o.skill, 0, progress.MAX_SKILLS - 1)
    kind = o.kind[index]
    running = (o.skill != DONE) & ~o.failed
    # The current skill's effects (spec 5.2) hold now, with the oracle's p0 and spatial parts.
    effects = progress.evaluate(data, geo, o.masks, rows, o.p0, facts).all()
    tcp = data.tcp_pos
    z_axis = quat_rotate(o.cmd_quat, jnp.array([0.0, 0.0, 1.0]))
    stage, steps = o.stage, o.stage_steps
    up = jnp.array([0.0, 0.0, 1.0])

    # The part the skill is about: its own, or for a push the part the touch before it touched.
    # Only the two clouds a step reads are moved to the world frame: the object's and the focus part's.
    whole_points, whole_valid = predicates.object_points(data, geo), geo.valid[geo.whole]
    push = (kind == MOVE) & o.touching[index]
    focus_part = jnp.maximum(jnp.where(push, o.part[jnp.maximum(index - 1, 0)], o.part[index]), 0)
    focus_points, focus_valid = predicates.part_cloud(data, geo, env_masks, focus_part)

    object_top = _top(whole_points, whole_valid)
    lowest = jnp.where(whole_valid, whole_points[:, 2], jnp.inf).min()
    # The task needs the object on the table (ON) while it is turned on the table or slid along it (SETTLE_GAP).
    settle = keep_on & (((kind == ROTATE) & o.on_table_turn[index])
                        | ((kind == MOVE) & o.grasping[index] & ~o.put_down[index]))
    down = settle & (lowest > TABLE_HEIGHT + SETTLE_GAP)
    on_table = lowest <= TABLE_HEIGHT + predicates.ON_TABLE_DISTANCE

    # Grasp / touch: 0 wait for a plan, 1 via point, 2 pre-pose, 3 approach, 4 close, 5 judge, 6 back off.
    pre, via = approach_waypoints(o.target_pos, o.approach)
    approach_goals = jnp.stack([o.cmd_pos, over_to(via, tcp, object_top), pre, o.target_pos, o.target_pos,
                                o.target_pos, pre])
    is_touch = kind == TOUCH
    reach_goal = approach_goals[jnp.clip(stage, 0, 6)]
    reach_speed = jnp.where(stage == 3, jnp.where(is_touch, PUSH_SPEED, APPROACH_SPEED), FREE_SPEED)
    reach_quat = jnp.where(stage == 0, o.cmd_quat, o.target_quat)
    reach_finger = jnp.where(is_touch | (stage == 4) | (stage == 5), panda.FINGER_CLOSED,
                             jnp.where((stage >= 1) & (stage <= 3), panda.finger_ctrl(o.target_open),
                                       panda.FINGER_OPEN))
    pos_r, quat_r = _toward(o.cmd_pos, o.cmd_quat, reach_goal, reach_quat, reach_speed, TURN_SPEED)
    at_goal = (jnp.linalg.norm(pos_r - reach_goal) < 1e-6) & (jnp.linalg.norm(tcp - reach_goal) < ARRIVED)
    reach_next = jnp.select(
        [stage == 1, stage == 2, stage == 3, stage == 4, stage == 5, stage == 6],
        [at_goal | (steps > 60), at_goal | (steps > 30),
         (jnp.linalg.norm(pos_r - reach_goal) < 1e-6) & ((jnp.linalg.norm(tcp - reach_goal) < 0.004) | (steps > 25)),
         steps >= CLOSE_STEPS, steps >= 10, at_goal | (steps > 20)], False)
    reach_done = reach_counted(effects, is_touch, stage, data.finger_qpos[0], o.grip_width)
    up_now = object_up(data.object_quat)
    tipping = is_touch & (stage == 3) & (steps > 0) & tipped(up_now, o.approach_up)
    reach_next = reach_next | tipping
    retry = reach_next & ((stage == 5) | (is_touch & (stage == 3)))
    reach_stage = jnp.where(retry, 6, jnp.where(reach_next & (stage == 6), 0, stage + reach_next.astype(jnp.int32)))
    replan = reach_next & (stage == 6)

    # Move: carry or push the object to p0 + 0.12 dir, or put it down until it rests on the table.
    direction = o.direction[index]
    goal_obj = o.p0 + UNIT_DISTANCE * direction
    error = goal_obj - data.object_pos
    push = o.touching[index]
    put_down = o.put_down[index]
    move_goal = jnp.where(put_down, o.cmd_pos - 0.02 * up, o.cmd_pos + error)
    # A carry starts slowly (the grip settles under the load) and speeds up.
    carry_speed = jnp.minimum(CARRY_SPEED, LIFT_START_SPEED + LIFT_ACCELERATION * steps)
    pos_c, _ = _toward(o.cmd_pos, o.cmd_quat, move_goal, o.cmd_quat, carry_speed, TURN_SPEED)
    # A push presses the touched part at its push point (pushing.py: low, near the line through the object's
    # middle) and drives the object along the line towards its goal; if the fingertip slips off it approaches the
    # (moved) push point again; if the touched part is not under the fingertip at the end it touches it again (the
    # task's TOUCHING names it): 0 back off, 1 pre-push pose, 2 approach until touching, 3 push, 4 behind the
    # touched part, 5 touch it. The touch before a push usually ends at the push point (then it starts at 3).
    push_pos, push_quat = o.target_pos, o.target_quat
    push_point, _ = pushing.push_point(focus_points, focus_valid, whole_points, whole_valid, direction)
    to_tcp = -predicates.FINGERTIP_OFFSET * quat_rotate(push_quat, up)
    touching_now = predicates.touching_points(data, whole_points, whole_valid)
    touching_part = predicates.touching_points(data, focus_points, focus_valid)
    # The fingers press the object (TOUCHING's fingertip point may still be more than 1 cm from it).
    pressing = predicates.finger_on_object(data, geo)
    # The object going along the push counts as touched: the hand itself may push it (a laptop's lid leaning over
    # the fingers), and the push then steers it like one the fingers make.
    advancing = push & ((data.object_pos - o.last_object) @ direction > PUSH_ADVANCING)
    in_contact = touching_now | pressing | advancing
    tip = tcp + predicates.FINGERTIP_OFFSET * quat_rotate(o.cmd_quat, up)
    # Pure pursuit: head for the point PUSH_LOOKAHEAD ahead of the object on the line p0 -> goal, so a sideways
    # drift is pushed back onto the line; the fingertip keeps to the line through the object's middle along it.
    flat = jnp.array([1.0, 1.0, 0.0])
    travelled = (data.object_pos - o.p0) @ direction
    aim = o.p0 + jnp.minimum(travelled + PUSH_LOOKAHEAD, UNIT_DISTANCE + PUSH_LOOKAHEAD) * direction
    heading = (aim - data.object_pos) * flat
    heading = heading / jnp.maximum(jnp.linalg.norm(heading), 1e-6)
    offset = (tip - pushing.footprint_centre(whole_points, whole_valid)) * flat
    lateral = offset - (offset @ heading) * heading
    steer = PUSH_SPEED * heading - jnp.clip(PUSH_STEER * lateral, -PUSH_STEER_LIMIT, PUSH_STEER_LIMIT)
    pushed_enough = travelled > UNIT_DISTANCE - PUSH_STOP
    retouch_point = rim_point(focus_points, focus_valid, direction, tip)
    tip_to_tcp = -predicates.FINGERTIP_OFFSET * z_axis
    back_off, to_pre_push, crossing = push_approach(o.anchor_pos, z_axis, push_pos - PUSH_BACK_OFF * direction,
                                                    o.cmd_pos, object_top)
    push_goals = jnp.stack([back_off, to_pre_push, push_point + TOUCH_PRESS * direction + to_tcp,
                            o.cmd_pos + jnp.where(pushed_enough, 0.0, steer),
                            retouch_point - RETOUCH_BACK * direction + tip_to_tcp,
                            retouch_point + RIM_OVER * direction + tip_to_tcp])
    push_stage = jnp.clip(stage, 0, 5)
    # Touching again stops once the part is touched or the fingers press the object (the pads may press it before
    # TOUCHING's fingertip point is near); a fingertip merely near the object goes on (it stopped 1.1 cm from a flat
    # scissors' blade, TOUCHING needs 1 cm, and stayed there).
    push_goal = jnp.where((push_stage == 5) & (touching_part | pressing), o.cmd_pos, push_goals[push_stage])
    push_goal = jnp.where(push_stage == 2, over_and_back(push_goal, o.cmd_pos, tip, push_point, direction, z_axis,
                                                         object_top, in_contact), push_goal)
    push_turn = jnp.where((push_stage == 1) | (push_stage == 2), push_quat, o.cmd_quat)
    push_speed = jnp.where((push_stage == 2) | (push_stage >= 3), PUSH_SPEED, FREE_SPEED)
    pos_p, quat_p = _toward(o.cmd_pos, o.cmd_quat, push_goal, push_turn, push_speed, TURN_SPEED)
    pos_m = jnp.where(push, pos_p, pos_c)
    quat_m = jnp.where(push, quat_p, o.cmd_quat)
    push_arrived = (jnp.linalg.norm(pos_p - push_goal) < 1e-6) & (jnp.linalg.norm(tcp - push_goal) < ARRIVED)
    push_next = jnp.select([push_stage == 0, push_stage == 1, push_stage == 2, push_stage == 3, push_stage == 4],
                           [push_arrived | (steps > 20), (push_arrived & ~crossing) | (steps > 60),
                            push_approached(in_contact, steps, tip, push_point, pushed_enough),
                            pushed_enough & ~touching_part, push_arrived | (steps > 20)], False)
    # Already touching where the push would start: push from there. Slipped off during the push: approach again.
    in_place = in_contact & (jnp.linalg.norm(tip - push_point) < PUSH_START_TOLERANCE)
    slipped = (push_stage == 3) & ~pushed_enough & (o.lost >= PUSH_SLIP_STEPS)
    move_stage = jnp.where(push, jnp.select([(push_stage == 0) & in_place, slipped], [3, 2], push_stage + push_next),
                           stage)
    move_done = jnp.where(push, push_counted(effects, touching_part | ~retouch, push_stage, pushed_enough),
                          effects & (put_down | (jnp.linalg.norm(error) < MOVE_TOLERANCE)) & (~settle | on_table))

    # Rotate: turn the hand so the part's direction from the object origin reaches the goal direction.
    vector = predicates.masked_mean(focus_points, focus_valid) - data.object_pos
    flat = o.on_table_turn[index]
    vector = jnp.where(flat, vector * jnp.array([1.0, 1.0, 0.0]), vector)
    vector = vector / jnp.maximum(jnp.linalg.norm(vector), 1e-9)
    cosine = jnp.clip(vector @ direction, -1.0, 1.0)
    angle = jnp.arccos(cosine)
    axis = jnp.cross(vector, direction)
    # Opposite vectors: turn about the vertical (the only axis a table turn has).
    axis = jnp.where(jnp.linalg.norm(axis) < 1e-3, up, axis)
    axis = jnp.where(flat, up * jnp.where(axis[2] >= 0, 1.0, -1.0), axis)
    axis = axis / jnp.linalg.norm(axis)
    turn_speed = TURN_START_SPEED + TURN_ACCELERATION * steps
    turn = axis_angle_to_quat(axis, jnp.minimum(angle, jnp.minimum(TURN_SPEED, turn_speed)))
    quat_t = quat_multiply(turn, o.cmd_quat)
    # 0 wait for the plan, 1 follow the planned turn, 2 closed-loop correction (shortest arc about the TCP),
    # 3 carry the object back (below).
    radius = jnp.linalg.norm(o.anchor_pos - o.turn_pivot)
    turn_step = (jnp.minimum(jnp.minimum(PLANNED_TURN_SPEED, turn_speed), CARRY_SPEED / jnp.maximum(radius, 1e-3))
                 / jnp.maximum(o.turn_angle, 1e-3))
    turn_progress = jnp.where(stage == 1, jnp.minimum(1.0, o.turn_progress + turn_step), o.turn_progress)
    pos_1, quat_1 = rotation.turned_pose(o.turn_pivot, o.turn_axis, o.turn_angle, turn_progress, o.anchor_pos,
                                         o.anchor_quat)
    pos_1 = pos_1 + o.turn_raise * jnp.minimum(1.0, 2.0 * turn_progress) * up
    # 3 carry the object back to where the turn started (on the table: sideways only; in the air: clear of it).
    back = (o.p0 - data.object_pos) * jnp.where(flat, jnp.array([1.0, 1.0, 0.0]), 1.0)
    back = jnp.where(flat, back, back.at[2].set(jnp.maximum(back[2], TABLE_HEIGHT + rotation.TABLE_CLEARANCE - lowest)))
    recentre_speed = jnp.minimum(CARRY_SPEED, RECENTRE_ACCELERATION * (steps + 1))
    pos_3, _ = _toward(o.cmd_pos, o.cmd_quat, o.anchor_pos, o.cmd_quat, recentre_speed, TURN_SPEED)
    pos_t = jnp.select([stage == 1, stage == 3], [pos_1, pos_3], o.cmd_pos)
    quat_t = jnp.select([stage == 1, stage >= 2], [quat_1, quat_t], o.cmd_quat)
    # Facing the goal after the planned turn (even where the arm cannot bring the TCP onto the plan's end pose: it
    # never arrived there, and the skill ran out of steps): done, or first carried back if the turn moved it away.
    faces = effects & (angle < ROTATE_TOLERANCE) & ((stage == 2) | ((stage == 1) & (turn_progress >= 1.0)))
    displaced = jnp.linalg.norm(back) > RECENTRE_START
    still_faces = effects & (angle < ROTATE_TOLERANCE)
    recentred = (jnp.linalg.norm(back) < RECENTRE_DONE) | (steps >= RECENTRE_STEPS)
    turn_stage = jnp.select([faces & displaced, (stage == 1) & (turn_progress >= 1.0)
                             & (jnp.linalg.norm(tcp - pos_1) < ARRIVED), (stage == 3) & recentred & ~still_faces],
                            [3, 2, 2], stage)
    rotate_done = ((faces & ~displaced) | ((stage == 3) & still_faces & recentred)) & (~settle | on_table)
    # The carry back heads for a goal fixed when it starts (the TCP then, moved by the object's offset): a goal
    # following the measured TCP ran away where the arm could not follow.
    anchor_pos = jnp.where((kind == ROTATE) & (stage != 3) & (turn_stage == 3), tcp + back, o.anchor_pos)

    # Release: open, back off along the TCP's z, then up.
    release_goals = jnp.stack([o.cmd_pos, o.target_pos - RETREAT_BACK * z_axis, o.target_pos + RETREAT_UP * up])
    release_goal = release_goals[jnp.clip(stage, 0, 2)]
    pos_l, _ = _toward(o.cmd_pos, o.cmd_quat, release_goal, o.cmd_quat, FREE_SPEED, TURN_SPEED)
    release_arrived = (jnp.linalg.norm(pos_l - release_goal) < 1e-6) & (jnp.linalg.norm(tcp - release_goal) < ARRIVED)
    release_next = jnp.where(stage == 0, (data.finger_qpos[0] > FINGER_OPENED) | (steps > 20),
                             release_arrived | (steps > 25))
    release_done = effects & (stage >= 2) & release_next

    pos = jnp.select([kind <= TOUCH, kind == MOVE, kind == ROTATE], [pos_r, pos_m, pos_t], pos_l)
    pos = pos.at[2].set(jnp.where(down, jnp.minimum(pos[2], tcp[2] - jnp.minimum(lowest - TABLE_HEIGHT, SETTLE_SPEED)),
                                  pos[2]))
    quat = jnp.select([kind <= TOUCH, kind == MOVE, kind == ROTATE], [quat_r, quat_m, quat_t], o.cmd_quat)
    holding = (kind == ROTATE) | ((kind == MOVE) & (o.grasping[index] | push))
    finger = jnp.select([kind <= TOUCH, kind == RELEASE, holding], [reach_finger, panda.FINGER_OPEN,
                                                                    panda.FINGER_CLOSED], o.finger)
    done = jnp.select([kind <= TOUCH, kind == MOVE, kind == ROTATE], [reach_done, move_done, rotate_done],
                      release_done)
    if follow_env:
        # Carries run their full 0.12 m (a carry stopped early swings the object off the fingers; the next move is
        # measured from the env's p0 anyway); other skills, pushes too, end once the env counts them (a bottle pushed
        # on past that by its back tipped over, and the release after it never came).
        done = done | ((env_skill > o.skill) & ((kind != MOVE) | push))
    next_stage = jnp.select([kind <= TOUCH, kind == MOVE, kind == RELEASE, kind == ROTATE],
                            [reach_stage, move_stage, jnp.minimum(stage + release_next, 2), turn_stage], stage)
    # Release starts from the pose it has now: remember it as the retreat's reference.
    target_pos = jnp.where((kind == RELEASE) & (stage == 0), o.cmd_pos, o.target_pos)
    attempt = o.attempt + replan
    out_of_attempts = replan & (attempt >= MAX_ATTEMPTS)
    # A turn carrying the object back ends by its own step count.
    over_budget = (o.skill_steps >= jnp.asarray(SKILL_BUDGET)[kind]) & ~((kind == ROTATE) & (stage == 3))
    # Carrying, pushing or turning without the object in hand fails at once (the original aborts such motions).
    needs_hold = ((kind == MOVE) & (o.grasping[index] | (push & (stage == 3) & ~pushed_enough))) | (kind == ROTATE)
    holds = jnp.where(push, in_contact, predicates.pressing(data, geo).any())  # GRASPING of the whole object
    lost = jnp.where(needs_hold & ~holds, o.lost + 1, 0)
    fail = running & ~done & (over_budget | out_of_attempts | (lost > LOST_STEPS))

    finished = running & done
    next_skill = jnp.where(o.skill + 1 >= o.num_skills, DONE, o.skill + 1)
    skill = jnp.where(finished, next_skill, o.skill)
    new_index = jnp.clip(skill, 0, progress.MAX_SKILLS - 1)
    new_kind = o.kind[new_index]
    starts_plan = finished & (skill != DONE) & ((new_kind <= TOUCH) | (new_kind == ROTATE)
                                                | ((new_kind == MOVE) & o.touching[new_index]))
    p0 = jnp.where(finished, starting_p0(o.kind, new_index, data.object_pos, task_p0, follow_env), o.p0)
    keep = ~running
    return o.replace(
        skill=skill,
        stage=jnp.where(finished, 0, jnp.where(keep, o.stage, next_stage)),
        stage_steps=jnp.where(finished | (next_stage != stage), 0, o.stage_steps + 1),
        skill_steps=jnp.where(finished, 0, o.skill_steps + 1),
        attempt=jnp.where(finished, 0, attempt), skip=jnp.where(finished, 0, o.skip), lost=jnp.where(finished, 0, lost),
        needs_plan=running & (o.needs_plan | starts_plan | (replan & ~out_of_attempts)),
        failed=o.failed | fail, failed_skill=jnp.where(fail, o.skill, o.failed_skill),
        p0=p0,
        cmd_pos=jnp.where(keep, o.cmd_pos, pos), cmd_quat=jnp.where(keep, o.cmd_quat, quat),
        finger=jnp.where(keep, o.finger, finger), grip_width=data.finger_qpos[0].astype(jnp.float32),
        target_pos=target_pos, anchor_pos=jnp.where(keep, o.anchor_pos, anchor_pos),
        turn_progress=jnp.where(finished, 0.0, turn_progress), last_object=data.object_pos.astype(jnp.float32),
        approach_up=jnp.where((stage == 3) & (steps == 0), up_now, o.approach_up).astype(jnp.float32))
