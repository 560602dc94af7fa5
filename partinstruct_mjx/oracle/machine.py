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
from partinstruct_mjx.oracle import candidates
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import TABLE_HEIGHT
from partinstruct_mjx.tasks import predicates, progress
from partinstruct_mjx.tasks.part_geometry import PartGeometry, spatial_masks
from partinstruct_mjx.tasks.vocabulary import OPPOSITE, UNIT_DISTANCE, direction_vector

GRASP, TOUCH, MOVE, ROTATE, RELEASE = range(5)
SKILL_KINDS = {"grasp_obj": GRASP, "touch_obj": TOUCH, "move_gripper": MOVE, "rotate_obj": ROTATE,
               "release_obj": RELEASE}
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
"""Commanded TCP speed limits per 20 Hz step (metres, radians)."""
ARRIVED = 0.012
"""Measured TCP distance to a waypoint that counts as arrived (the servos lag the command)."""
VIA_HEIGHT = 0.06
"""Waypoints before a pregrasp/pretouch pose are raised this much, so the hand comes from above."""
CLOSE_STEPS = 14
"""Steps the fingers get to close (0.25 s filter) before the grasp is judged."""
MOVE_TOLERANCE = 0.012
"""The oracle's own move ends within this of p0 + 0.12 dir (the effect allows 0.05)."""
ROTATE_TOLERANCE = 0.2
"""Radians between the part's direction and the goal at which a rotation ends (FACING allows 0.5)."""
RETREAT_BACK = 0.05
RETREAT_UP = 0.10
"""Release: back off along the TCP's z, then up (spec 8.8, the oracle config's 0.1 m)."""
FINGER_OPENED = 0.035
LOST_STEPS = 6
PUSH_TILT = 0.9
PUSH_HEIGHT = 0.025
"""Pushes press with the hand tilted down this much (rad), this high (m) above the table at least."""
PUSH_BACK_OFF = 0.04
TOUCH_PRESS = 0.01
"""Metres the fingertip leaves the object before re-approaching it low, and how far past the face it aims."""
"""Steps a carry, push or turn may go on without holding (or touching) the object before the skill fails."""


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
    lost: jnp.ndarray          # (B,) consecutive steps without the grasp/touch a skill needs
    needs_plan: jnp.ndarray
    failed: jnp.ndarray
    failed_skill: jnp.ndarray  # (B,) index of the skill that failed, -1
    p0: jnp.ndarray            # (B, 3) object position when the skill started
    masks: jnp.ndarray         # (B, 7, M) spatial parts sampled when the skill started
    cmd_pos: jnp.ndarray
    cmd_quat: jnp.ndarray
    finger: jnp.ndarray
    target_pos: jnp.ndarray   # grasp/touch TCP pose from the planner
    target_quat: jnp.ndarray
    approach: jnp.ndarray     # (B, 3) unit axis the TCP moves along into the target
    key: jnp.ndarray


def compile_chains(episodes, geometry: PartGeometry) -> dict[str, np.ndarray]:
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
                out["part"][b, s] = geometry.index(step.part)
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
        **fields, skill=zeros, stage=zeros, stage_steps=zeros, skill_steps=zeros, attempt=zeros, lost=zeros,
        needs_plan=jnp.asarray(np.isin(chains["kind"][:, 0], (GRASP, TOUCH))), failed=jnp.zeros(batch, bool),
        failed_skill=jnp.full(batch, -1, jnp.int32), p0=jnp.asarray(data.object_pos, jnp.float32), masks=masks,
        cmd_pos=jnp.asarray(data.tcp_pos, jnp.float32), cmd_quat=jnp.asarray(data.tcp_quat, jnp.float32),
        finger=jnp.asarray(data.finger_qpos[:, 0], jnp.float32),
        target_pos=jnp.asarray(data.tcp_pos, jnp.float32), target_quat=jnp.asarray(data.tcp_quat, jnp.float32),
        approach=jnp.zeros((batch, 3), jnp.float32), key=jnp.asarray(keys))


# --- planning -----------------------------------------------------------------------------------------------


def plan(oracle: OracleState, data, geometry: PartGeometry, kinematics, joint_targets) -> OracleState:
    """Choose the grasp or touch pose of every environment that asks for one (`needs_plan`); the others pass through.

    The `attempt`-th reachable candidate in rank order is taken; none left fails the skill.
    """
    return jax.vmap(_plan_one, in_axes=(0, 0, None, None, 0))(oracle, data, geometry, kinematics, joint_targets)


def _plan_one(o: OracleState, data, geo: PartGeometry, kinematics, q):
    index = jnp.clip(o.skill, 0, progress.MAX_SKILLS - 1)
    kind, part = o.kind[index], jnp.maximum(o.part[index], 0)
    world = predicates.world_clouds(data, geo)
    whole = geo.whole
    object_points, object_valid = world[whole][::2], geo.valid[whole][::2]
    object_normals = quat_rotate(data.body_quat[geo.bodies[whole][::2]], geo.normals[whole][::2])
    part_points, part_valid = predicates.part_cloud(data, geo, o.masks, part, world)
    part_normals = quat_rotate(data.body_quat[geo.bodies[part]], geo.normals[part])
    key, sub = jax.random.split(o.key)

    grasps = candidates.grasp_candidates(object_points, object_normals, object_valid, part_points, part_normals,
                                          part_valid, sub)
    top_score, top = jax.lax.top_k(grasps["score"], PLAN_CANDIDATES)
    approach, closing = grasps["approach"][top], grasps["closing"][top]
    # Of the two equivalent closing directions take the one nearer the current hand orientation.
    quat_a = candidates.tcp_quat(approach, closing)
    quat_b = candidates.tcp_quat(approach, -closing)
    turn_a = jnp.linalg.norm(quat_error(quat_a, o.cmd_quat[None]), axis=-1)
    turn_b = jnp.linalg.norm(quat_error(quat_b, o.cmd_quat[None]), axis=-1)
    grasp_quat = jnp.where((turn_a <= turn_b)[:, None], quat_a, quat_b)
    grasp_pos = grasps["centre"][top] - candidates.PAD_CENTRE * approach
    grasp_ok = jnp.isfinite(top_score)

    touches = candidates.touch_candidates(object_points, object_valid, part_points, part_valid, o.push_side[index])
    touch_point, touch_axis, touch_score = touches
    touch_order = jnp.argsort(-touch_score)
    touch_axis = touch_axis[touch_order]
    touch_quat = jax.vmap(candidates.touch_quat)(touch_axis)
    tip = predicates.FINGERTIP_OFFSET - candidates.TOUCH_DEPTH
    touch_pos = touch_point[touch_order] - tip * touch_axis
    touch_ok = jnp.isfinite(touch_score[touch_order])

    is_grasp = kind == GRASP
    pad = grasp_pos.shape[0] - touch_pos.shape[0]
    positions = jnp.where(is_grasp, grasp_pos, jnp.pad(touch_pos, ((0, pad), (0, 0))))
    quats = jnp.where(is_grasp, grasp_quat, jnp.pad(touch_quat, ((0, pad), (0, 0))))
    axes = jnp.where(is_grasp, approach, jnp.pad(touch_axis, ((0, pad), (0, 0))))
    ok = jnp.where(is_grasp, grasp_ok, jnp.pad(touch_ok, (0, pad)))
    reachable = ok & jax.vmap(_reachable, in_axes=(None, None, 0, 0, 0))(kinematics, q, positions, quats, axes)
    rank = jnp.cumsum(reachable) - 1
    chosen = reachable & (rank == o.attempt)
    found = chosen.any()
    pick = jnp.argmax(chosen)
    fail = o.needs_plan & ~found
    take = o.needs_plan & found
    return o.replace(
        target_pos=jnp.where(take, positions[pick], o.target_pos),
        target_quat=jnp.where(take, quats[pick], o.target_quat),
        approach=jnp.where(take, axes[pick], o.approach),
        stage=jnp.where(take, 1, o.stage), stage_steps=jnp.where(take, 0, o.stage_steps),
        needs_plan=jnp.zeros_like(o.needs_plan), key=key,
        failed=o.failed | fail, failed_skill=jnp.where(fail & ~o.failed, o.skill, o.failed_skill))


REACH_CONFIG = jax_ik.IKConfig(iterations=40)
PLAN_CANDIDATES = 16
"""Best-ranked grasps whose reach is checked with the IK."""


def _reachable(kinematics, q, position, quat, axis):
    """The IK reaches the via point, the pre-pose and the pose itself, each from the previous solution."""
    pre = position - candidates.PREGRASP_DISTANCE * axis
    ok = jnp.asarray(True)
    for target in (pre + jnp.array([0.0, 0.0, VIA_HEIGHT]), pre, position):
        q, position_error, rotation_error = jax_ik._solve_one(kinematics, REACH_CONFIG, q, target, quat)
        ok = ok & (position_error < 0.005) & (rotation_error < 0.05)
    return ok


# --- acting -------------------------------------------------------------------------------------------------


def act(oracle: OracleState, data, skill_rows: progress.GoalRows, geometry: PartGeometry,
        task: progress.TaskState | None = None) -> tuple[OracleState, jnp.ndarray]:
    """One step of every environment's machine: the new state and the (B, 7) Euler pose actions.

    skill_rows: the episodes' skill effects, `TaskState.skills` (B, MAX_SKILLS, MAX_GOALS). task: an env in skill
    mode passes its progress; the machine then follows the env's skill chain (a skill ends when the env counts it,
    judged from the env's p0 and spatial parts) instead of its own tolerances.
    """
    follow = (oracle.skill, oracle.p0, oracle.masks) if task is None else (task.skill_index, task.skill_p0,
                                                                           task.masks)
    before = oracle.skill
    oracle = jax.vmap(partial(_act_one, follow_env=task is not None), in_axes=(0, 0, None, 0, 0, 0))(
        oracle, data, geometry, skill_rows, follow, _push_poses(oracle, data, geometry))
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


def _push_poses(oracle: OracleState, data, geo: PartGeometry):
    """`_push_pose` of every environment, computed only on steps where some push is still placing its fingertip."""
    index = jnp.clip(oracle.skill, 0, progress.MAX_SKILLS - 1)[:, None]
    pushing = ((jnp.take_along_axis(oracle.kind, index, axis=1)[:, 0] == MOVE)
               & jnp.take_along_axis(oracle.touching, index, axis=1)[:, 0] & (oracle.stage < 3)
               & (oracle.skill != DONE) & ~oracle.failed)
    direction = jnp.take_along_axis(oracle.direction, index[:, :, None], axis=1)[:, 0]
    batch = direction.shape[0]
    return jax.lax.cond(
        pushing.any(), lambda: jax.vmap(_push_pose, in_axes=(0, None, 0))(data, geo, direction),
        lambda: (jnp.zeros((batch, 3), jnp.float32), jnp.zeros((batch, 4), jnp.float32).at[:, 0].set(1.0),
                 jnp.zeros(batch, jnp.float32)))


def _push_pose(data, geo: PartGeometry, direction):
    """TCP pose (position, quaternion) that puts the fingertip (hand tilted down by PUSH_TILT, facing the push) on
    the lowest point of the object's face opposite the push, at least PUSH_HEIGHT above the table; and that point's
    height."""
    world = predicates.world_clouds(data, geo)
    points, valid = world[geo.whole], geo.valid[geo.whole]
    reach = jnp.where(valid, -(points @ direction), -jnp.inf)
    face = valid & (reach > reach.max() - candidates.FACE_BAND) & (points[:, 2] > TABLE_HEIGHT + PUSH_HEIGHT)
    # Low, and in line with the object's centre along the push (an off-centre push turns the object away).
    offset = points - predicates.masked_mean(points, valid)
    lateral = offset - (offset @ direction)[:, None] * direction
    cost = points[:, 2] + 2.0 * jnp.linalg.norm(lateral[:, :2], axis=-1)
    point = points[jnp.argmin(jnp.where(face, cost, jnp.inf))]
    z_axis = jnp.cos(PUSH_TILT) * direction - jnp.sin(PUSH_TILT) * jnp.array([0.0, 0.0, 1.0])
    pos = point - predicates.FINGERTIP_OFFSET * z_axis
    return pos.astype(jnp.float32), candidates.touch_quat(z_axis).astype(jnp.float32), point[2].astype(jnp.float32)


def _skill_effects(o: OracleState, data, geo: PartGeometry, rows) -> jnp.ndarray:
    """The current skill's effects (spec 5.2) hold now, with the oracle's p0 and spatial parts."""
    return progress.evaluate(data, geo, o.masks, rows, o.p0).all()


def _act_one(o: OracleState, data, geo: PartGeometry, rows, env, push_pose, follow_env: bool):
    env_skill, env_p0, env_masks = env
    if follow_env:
        # While the machine is on the env's skill it judges it as the env does; once the env has counted a skill the
        # machine still finishes it (see below) with the p0 it had.
        synced = env_skill == o.skill
        o = o.replace(p0=jnp.where(synced, env_p0, o.p0), masks=jnp.where(synced, env_masks, o.masks))
    index = jnp.clip(o.skill, 0, progress.MAX_SKILLS - 1)
    kind = o.kind[index]
    running = (o.skill != DONE) & ~o.failed
    effects = _skill_effects(o, data, geo, jax.tree_util.tree_map(lambda x: x[index], rows))
    tcp = data.tcp_pos
    z_axis = quat_rotate(o.cmd_quat, jnp.array([0.0, 0.0, 1.0]))
    stage, steps = o.stage, o.stage_steps
    up = jnp.array([0.0, 0.0, 1.0])

    # Grasp / touch: 0 wait for a plan, 1 via point, 2 pre-pose, 3 approach, 4 close, 5 judge, 6 back off.
    pre = o.target_pos - candidates.PREGRASP_DISTANCE * o.approach
    approach_goals = jnp.stack([o.cmd_pos, pre + VIA_HEIGHT * up, pre, o.target_pos, o.target_pos, o.target_pos, pre])
    is_touch = kind == TOUCH
    reach_goal = approach_goals[jnp.clip(stage, 0, 6)]
    reach_speed = jnp.where(stage == 3, jnp.where(is_touch, PUSH_SPEED, APPROACH_SPEED), FREE_SPEED)
    reach_quat = jnp.where(stage == 0, o.cmd_quat, o.target_quat)
    reach_finger = jnp.where(is_touch, panda.FINGER_CLOSED,
                             jnp.where((stage == 4) | (stage == 5), panda.FINGER_CLOSED, panda.FINGER_OPEN))
    pos_r, quat_r = _toward(o.cmd_pos, o.cmd_quat, reach_goal, reach_quat, reach_speed, TURN_SPEED)
    at_goal = (jnp.linalg.norm(pos_r - reach_goal) < 1e-6) & (jnp.linalg.norm(tcp - reach_goal) < ARRIVED)
    reach_next = jnp.select(
        [stage == 1, stage == 2, stage == 3, stage == 4, stage == 5, stage == 6],
        [at_goal | (steps > 60), at_goal | (steps > 30),
         (jnp.linalg.norm(pos_r - reach_goal) < 1e-6) & ((jnp.linalg.norm(tcp - reach_goal) < 0.004) | (steps > 25)),
         steps >= CLOSE_STEPS, steps >= 10, at_goal | (steps > 20)], False)
    # A touch is judged as it approaches: it is done the moment TOUCHING holds.
    reach_done = effects & jnp.where(is_touch, stage >= 2, stage >= 4)
    retry = reach_next & ((stage == 5) | (is_touch & (stage == 3)))
    reach_stage = jnp.where(retry, 6, jnp.where(reach_next & (stage == 6), 0, stage + reach_next.astype(jnp.int32)))
    replan = reach_next & (stage == 6)

    # Move: carry or push the object to p0 + 0.12 dir, or put it down until it rests on the table.
    direction = o.direction[index]
    goal_obj = o.p0 + UNIT_DISTANCE * direction
    error = goal_obj - data.object_pos
    push = o.touching[index]
    correction = jnp.where(push, direction * (error @ direction), error)
    put_down = o.put_down[index]
    move_goal = jnp.where(put_down, o.cmd_pos - 0.02 * up, o.cmd_pos + correction)
    move_speed = jnp.where(push, PUSH_SPEED, CARRY_SPEED)
    # A push first moves the fingertip low on the object (the touched part may be high up: pushing there tips tall
    # objects over): 0 back off, 1 pre-push pose, 2 approach until touching, 3 push.
    push_pos, push_quat, push_height = push_pose
    tip_height = (tcp + predicates.FINGERTIP_OFFSET * quat_rotate(o.cmd_quat, up))[2]
    push_goals = jnp.stack([o.target_pos - PUSH_BACK_OFF * direction + PUSH_BACK_OFF * up,
                            push_pos - PUSH_BACK_OFF * direction, push_pos + TOUCH_PRESS * direction, move_goal])
    push_stage = jnp.clip(stage, 0, 3)
    push_goal = push_goals[push_stage]
    push_turn = jnp.where(push_stage == 0, o.cmd_quat, push_quat)
    pos_p, quat_p = _toward(o.cmd_pos, o.cmd_quat, push_goal, push_turn, jnp.where(push_stage >= 2, PUSH_SPEED,
                                                                                    FREE_SPEED), TURN_SPEED)
    pos_c, _ = _toward(o.cmd_pos, o.cmd_quat, move_goal, o.cmd_quat, move_speed, TURN_SPEED)
    pos_m = jnp.where(push & (push_stage < 3), pos_p, pos_c)
    quat_m = jnp.where(push & (push_stage < 3), quat_p, o.cmd_quat)
    push_arrived = (jnp.linalg.norm(pos_p - push_goal) < 1e-6) & (jnp.linalg.norm(tcp - push_goal) < ARRIVED)
    touching_now = predicates.touching(data, geo, o.masks, geo.whole)
    push_next = jnp.select([push_stage == 0, push_stage == 1, push_stage == 2],
                           [push_arrived | (steps > 20), push_arrived | (steps > 30), touching_now | (steps > 30)],
                           False)
    # Already touching low down: push from where the fingertip is.
    move_stage = jnp.where(push, jnp.where((push_stage == 0) & touching_now & (tip_height < push_height + 0.02), 3,
                                           push_stage + push_next), stage)
    move_done = effects & (put_down | (jnp.linalg.norm(error) < MOVE_TOLERANCE)) & (~push | (push_stage == 3))

    # Rotate: turn the hand so the part's direction from the object origin reaches the goal direction.
    part_points, part_valid = predicates.part_cloud(data, geo, o.masks, jnp.maximum(o.part[index], 0))
    vector = predicates.masked_mean(part_points, part_valid) - data.object_pos
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
    turn = axis_angle_to_quat(axis, jnp.minimum(angle, TURN_SPEED))
    quat_t = quat_multiply(turn, o.cmd_quat)
    rotate_done = effects & (angle < ROTATE_TOLERANCE)

    # Release: open, back off along the TCP's z, then up.
    release_goals = jnp.stack([o.cmd_pos, o.target_pos - RETREAT_BACK * z_axis, o.target_pos + RETREAT_UP * up])
    release_goal = release_goals[jnp.clip(stage, 0, 2)]
    pos_l, _ = _toward(o.cmd_pos, o.cmd_quat, release_goal, o.cmd_quat, FREE_SPEED, TURN_SPEED)
    release_arrived = (jnp.linalg.norm(pos_l - release_goal) < 1e-6) & (jnp.linalg.norm(tcp - release_goal) < ARRIVED)
    release_next = jnp.where(stage == 0, (data.finger_qpos[0] > FINGER_OPENED) | (steps > 20),
                             release_arrived | (steps > 25))
    release_done = effects & (stage >= 2) & release_next

    pos = jnp.select([kind <= TOUCH, kind == MOVE, kind == ROTATE], [pos_r, pos_m, o.cmd_pos], pos_l)
    quat = jnp.select([kind <= TOUCH, kind == MOVE, kind == ROTATE], [quat_r, quat_m, quat_t], o.cmd_quat)
    holding = (kind == ROTATE) | ((kind == MOVE) & (o.grasping[index] | push))
    finger = jnp.select([kind <= TOUCH, kind == RELEASE, holding], [reach_finger, panda.FINGER_OPEN,
                                                                    panda.FINGER_CLOSED], o.finger)
    done = jnp.select([kind <= TOUCH, kind == MOVE, kind == ROTATE], [reach_done, move_done, rotate_done],
                      release_done)
    if follow_env:
        # Moves run their full 0.12 m (a carry stopped early swings the object off the fingers; the next move is
        # measured from the env's p0 anyway); other skills end once the env counts them.
        done = done | ((env_skill > o.skill) & (kind != MOVE))
    next_stage = jnp.select([kind <= TOUCH, kind == MOVE, kind == RELEASE],
                            [reach_stage, move_stage, jnp.minimum(stage + release_next, 2)], stage)
    # Release starts from the pose it has now: remember it as the retreat's reference.
    target_pos = jnp.where((kind == RELEASE) & (stage == 0), o.cmd_pos, o.target_pos)
    attempt = o.attempt + replan
    out_of_attempts = replan & (attempt >= MAX_ATTEMPTS)
    over_budget = o.skill_steps >= jnp.asarray(SKILL_BUDGET)[kind]
    # Carrying, pushing or turning without the object in hand fails at once (the original aborts such motions).
    needs_hold = ((kind == MOVE) & (o.grasping[index] | (push & (stage >= 3)))) | (kind == ROTATE)
    holds = jnp.where(push, touching_now, predicates.grasping(data, geo, o.masks, geo.whole))
    lost = jnp.where(needs_hold & ~holds, o.lost + 1, 0)
    fail = running & ~done & (over_budget | out_of_attempts | (lost > LOST_STEPS))

    finished = running & done
    next_skill = jnp.where(o.skill + 1 >= o.num_skills, DONE, o.skill + 1)
    skill = jnp.where(finished, next_skill, o.skill)
    new_index = jnp.clip(skill, 0, progress.MAX_SKILLS - 1)
    starts_reach = finished & (skill != DONE) & (o.kind[new_index] <= TOUCH)
    keep = ~running
    return o.replace(
        skill=skill,
        stage=jnp.where(finished, 0, jnp.where(keep, o.stage, next_stage)),
        stage_steps=jnp.where(finished | (next_stage != stage), 0, o.stage_steps + 1),
        skill_steps=jnp.where(finished, 0, o.skill_steps + 1),
        attempt=jnp.where(finished, 0, attempt), lost=jnp.where(finished, 0, lost),
        needs_plan=running & (starts_reach | (replan & ~out_of_attempts)),
        failed=o.failed | fail, failed_skill=jnp.where(fail, o.skill, o.failed_skill),
        p0=jnp.where(finished, data.object_pos, o.p0),
        cmd_pos=jnp.where(keep, o.cmd_pos, pos), cmd_quat=jnp.where(keep, o.cmd_quat, quat),
        finger=jnp.where(keep, o.finger, finger),
        target_pos=target_pos)
