"""Which parts and directions make sense for an object at a pose: the slot rules of episode generation.

Part slots get a role from the skill that uses them (grasp_obj, touch_obj, rotate_obj); direction slots from the
skill they parameterise (a carry, a push, a rotation in the air or on the table). Rules, all from the object's part
points as it rests on the table (its rest configuration dropped and settled, as the environment does at reset: a
flat object settles a few degrees tilted, which decides whether the pads fit under its raised end) turned by the
episode's yaw:

* exposed: an approach direction (left, right, front, back, top; never from below) is free when the part's box,
  grown by 0.1 x its diagonal, reaches as far along it as the rest of the object at the part's level: the object
  points within the part's height range for a side approach, over the part's footprint for the top one (the
  oracle's touch test, spec 8.5, compares with the whole object's box, which hides e.g. a bottle's neck behind
  its wider body);
* never a cavity (CAVITIES) or 'middle'; never grasped or touched at the 'bottom' (it rests on the table);
* grasp: exposed, not in GRASP_EXCLUDED, and `graspable`: the oracle's grasp search finds grasps the Panda hand
  can close on (a section under 7.4 cm, pads and hand free of the object, pads above the table, landing faces
  facing the pads); a 2 mm scissors blade lying flat, or a pot's wall under its lid, are not. `feasible_assignments`
  applies the cheap rules; the episode generator asks `graspable` only for the parts of the assignment it draws;
* reach (asked by the generator of the drawn chain, tasks/episodes.py `chain_reachable`): the arm, from its home
  pose, reaches one of the oracle's first grasps on a grasped part (`grasp_reachable`) and one of its touch poses on
  a touched part (`touch_reachable`), where the chain's pushes and carries before have moved the object; and a grasp
  followed by a turn in the air needs one of the oracle's grasps whose look-ahead fits the turn (`air_turn_fits`);
* touch: exposed;
* rotate: centroid >= 2 cm from the object origin (FACING is measured from it);
  in the air any direction but the one the part faces now, and where the object is put down after the turn
  (types 11, 12, 16) only directions the part can face (within FACING's threshold) with the object on the table
  and its origin within the put-down's AT threshold of the height it rests at now (a knife's blade cannot face
  up with the knife lying down, and standing on its end the knife's origin is 9 cm too high); on the table only
  horizontal ones and only for parts that face a horizontal direction now and lie within
  MAX_TABLE_TURN_ELEVATION of level (a yaw turn changes neither a part that faces up nor how far its centroid lies
  above or below the origin, and FACING allows 0.5 rad in all); type 15 turns the part to the opposite of the
  direction it faces now;
* move / push: horizontal, the object stays in the workspace (p0 + 0.12 dir within WORKSPACE); a push towards dir
  touches the part from the other side, so the part must be exposed on OPPOSITE[dir] and have a push point there
  (oracle/pushing.py: low enough not to tip the object, near the line through its middle);
* the parts of one episode are distinct (the paper rotates a part while holding another one).

Test 3 holds out part combinations (see `held_out_combinations`).
"""

from __future__ import annotations

import functools
import itertools
import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType, SimpleNamespace

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from partinstruct_mjx.control import jax_ik
from partinstruct_mjx.errors import AssetError
from partinstruct_mjx.oracle import candidates, lookahead, machine, pushing
from partinstruct_mjx.oracle.kinds import RELEASE, ROTATE
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
from partinstruct_mjx.sim.panda import HOME_ARM_QPOS
from partinstruct_mjx.sim.scene import TABLE_HEIGHT, SceneConfig, build_scene
from partinstruct_mjx.tasks.instructions import instruction_slots
from partinstruct_mjx.tasks.part_geometry import spatial_masks
from partinstruct_mjx.tasks.task_types import FACING_THRESHOLD, task_type
from partinstruct_mjx.tasks.vocabulary import (DIRECTIONS, HORIZONTAL, OPPOSITE, SPATIAL_PARTS, UNIT_DISTANCE,
                                                nearest_direction)

GRASP_EXCLUDED: dict[str, frozenset[str]] = {
    "laptop": frozenset({"keyboard", "touchpad", "screen"}),  # flush panels: nothing to close the fingers on
    "display": frozenset({"screen"}),  # flush panel inside the frame
    "scissors": frozenset({"screw"}),  # pivot pin flush with the blades
}
"""Semantic parts per category that a two-finger gripper cannot close on although their box is thin."""

CAVITIES = frozenset({"containing things"})
"""The inside of a container: nothing to close the fingers on, reachable only through the opening, facing nowhere."""

SPATIAL_WORDS = tuple(DIRECTIONS)
"""Spatial parts used by generation ('middle' is never a slot value; it only exists for reading other files)."""

APPROACHES = ("left", "right", "front", "back", "top")
"""Directions the gripper comes from (never from below the table)."""

AIR_TURN_KEYS = 6
"""Grasp searches `air_turn_fits` looks through (each the oracle's candidates for one random key)."""
AIR_TURN_CHUNK = 4
"""Grasp poses `air_turn_fits` checks at once, chunk after chunk until one fits (a chunk costs about as much as one
pose on a CPU core: the look-ahead's IK is vectorised)."""
GRASP_CHECK_KEYS = 4
MIN_GRASP_KEYS = 4
"""A part is graspable when the oracle's candidate search (candidates.NUM_SEEDS random seed points, as the oracle
draws them per attempt) finds a valid grasp on it for at least MIN_GRASP_KEYS of GRASP_CHECK_KEYS fixed keys: a
part with grasps in only a sliver of its surface would leave the oracle's plan to luck. Of the 715 episodes of
docs/oracle.md's 880 that grasp, the 65 whose part had no grasp under one of 4 keys (a bucket's body under its
raised handle, a pot's ears, a stapler's body under its lid) lost 43 in the grasp; 2 of 2 keys let them in."""
YAW_STEP = math.radians(5.0)
"""Spatial parts are judged for graspability at the episode's yaw rounded to this."""

MIN_FACING_OFFSET = 0.02
"""Closest a rotated part's centroid may be to the object origin (m) for FACING to be well defined."""
MAX_TABLE_TURN_ELEVATION = 0.4
"""Largest angle (rad) between a part's FACING vector and the horizontal for a turn on the table: a yaw turn keeps
that angle, and FACING (0.5 rad) must still hold with the oracle's heading tolerance (0.2 rad). A standing bottle's
'front' lies 2.9 cm out and 2.5 cm below its origin (0.71 rad): no turn on the table could make it face right."""
PUT_DOWN_AT_THRESHOLD = next(goal.threshold for goal in task_type(11).phases[-1] if goal.kind == "AT")
"""AT's threshold (m) in the put-down phase of the types that turn the object in the air and put it down (11, 12,
16; taken from type 11's goals): how much higher above the object's lowest point its origin may end than where it
rests now."""
NUM_UP_SAMPLES = 4000
"""Object orientations (which of its directions points up; evenly spread) searched for a put-down pose."""
WORKSPACE = ((-0.2, 0.25), (-0.25, 0.35))
"""x and y bounds a move or push must keep the object in."""

OPPOSITE_TYPES = frozenset({15})
"""Types whose rotation target is the opposite of the part's initial facing (paper: FACING(part, ~DIR_INIT))."""

HELD_OUT_FRACTION = 0.25
"""Share of each (category, type)'s part combinations that only Test 3 uses."""


@dataclass(frozen=True)
class ObjectGeometry:
    """Surface points and outward normals of an object at rest (all joints at 0) in its root frame, per semantic
    part and whole.

    Arrays are (3, N): reductions over points run along contiguous rows.
    """

    part_names: tuple[str, ...]
    part_points: tuple[np.ndarray, ...]
    object_points: np.ndarray
    part_normals: tuple[np.ndarray, ...]
    object_normals: np.ndarray
    resting_rise: np.ndarray
    """(NUM_UP_SAMPLES,) how much higher (m) the origin sits above the object's lowest point with UP_SAMPLES[k] (root
    frame) pointing up than at rest."""


@dataclass(frozen=True)
class PartView:
    """What the slot rules need to know about one part at the episode's initial pose."""

    offset: np.ndarray
    """World-frame vector from the object origin to the part centroid (FACING's vector)."""
    facing: str
    """The direction word nearest to `offset`: where the part faces at the initial pose."""
    exposed: frozenset[str]
    """Approach directions from which the part is free."""
    pushable: frozenset[str]
    """Horizontal directions a fingertip on the part can push the object along (oracle/pushing.py: pressing low
    enough not to tip it, near the line through its middle)."""
    put_down_facing: frozenset[str]
    """Directions the part can face (FACING_THRESHOLD) with the object on the table and its origin less than
    PUT_DOWN_AT_THRESHOLD higher above the object's lowest point than now."""


@functools.lru_cache(maxsize=None)
def load_object_geometry(object_dir: str) -> ObjectGeometry:
    """Read parts.npz and move every point from its body's frame into the root frame at the rest pose, tilted as
    the object settles on the table (`settled_tilt`)."""
    folder = Path(object_dir)
    try:
        model = mujoco.MjModel.from_xml_path(str(folder / "object.xml"))
        with np.load(folder / "parts.npz") as arrays:
            data = {key: arrays[key] for key in arrays.files}
    except (OSError, ValueError, KeyError) as err:
        raise AssetError(f"{folder}: cannot read object.xml / parts.npz ({err})") from err
    state = mujoco.MjData(model)
    mujoco.mj_kinematics(model, state)
    body_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, str(name)) for name in data["body_names"]]
    rotations, origins = state.xmat.reshape(-1, 3, 3)[body_ids], state.xpos[body_ids]
    tilt = settled_tilt(folder / "object.xml")
    rotations, origins = tilt @ rotations, origins @ tilt.T

    def to_root(points, bodies, moved=True):
        turned = np.einsum("nij,nj->ni", rotations[bodies], points)
        return np.ascontiguousarray((turned + origins[bodies] if moved else turned).T)

    object_points = to_root(data["object_points"], data["object_point_body"])
    return ObjectGeometry(tuple(str(n) for n in data["part_names"]),
                          tuple(to_root(p, b) for p, b in zip(data["points"], data["point_body"])),
                          object_points,
                          tuple(to_root(n, b, False) for n, b in zip(data["normals"], data["point_body"])),
                          to_root(data["object_normals"], data["object_point_body"], False),
                          _resting_rise(object_points))


def _up_samples(count: int) -> np.ndarray:
    """(count, 3) unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * i / count), math.pi * (1.0 + math.sqrt(5.0)) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)


UP_SAMPLES = _up_samples(NUM_UP_SAMPLES)


def _resting_rise(object_points: np.ndarray) -> np.ndarray:
    """ObjectGeometry.resting_rise of the root-frame points (3, N) of the object at rest."""
    return (-(UP_SAMPLES @ object_points).min(axis=1) + object_points[2].min()).astype(np.float32)


def settled_tilt(object_xml: Path) -> np.ndarray:
    """(3, 3) rotation of the object resting on the table after the environment's reset (dropped unturned at the
    default position, settled for `settle_steps` with the C backend), its yaw taken out."""
    with MujocoBackend(build_scene(SceneConfig(object_xml=object_xml)), 1) as backend:
        quat = np.asarray(backend.reset().object_quat[0], float)
    settled = np.zeros(9)
    mujoco.mju_quat2Mat(settled, quat)
    settled = settled.reshape(3, 3)
    heading = math.atan2(settled[1, 0], settled[0, 0])
    return yaw_matrix(-heading) @ settled


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation about the world z axis."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


_APPROACH_AXES = np.array([DIRECTIONS[word] for word in APPROACHES])
_spatial_masks = jax.jit(spatial_masks)


def part_views(geometry: ObjectGeometry, yaw: float) -> dict[str, PartView]:
    """Every semantic part and every spatial part (but 'middle', computed from the turned object's points as the
    original does at reset) of the object turned by `yaw`."""
    rotation = yaw_matrix(yaw)
    world = rotation @ geometry.object_points
    points = dict(zip(geometry.part_names, geometry.part_points))
    masks = np.asarray(_spatial_masks(world.T))
    points.update({word: geometry.object_points[:, masks[SPATIAL_PARTS.index(word)]] for word in SPATIAL_WORDS})
    return {name: _view(local, rotation, world, geometry.resting_rise) for name, local in points.items()}


def graspable(object_dir: str, yaw: float, part: str) -> bool:
    """The gripper can close on `part` of the object resting on the table turned by `yaw`: the oracle's grasp
    search (oracle/candidates.py: something between the pads, pads and hand free of the object, above the table,
    antipodal landing faces) finds grasps on it (MIN_GRASP_KEYS). The arm's reach is `grasp_reachable`'s.

    Deterministic (fixed keys). A semantic part is judged once per object, at yaw 0 (its shape does not turn with
    the yaw); a spatial part is a region of the turned object, so it is judged at `yaw` rounded to YAW_STEP (each
    judgement is cached: the search costs about 0.2 s on a CPU core).
    """
    _, grasps = _best_grasps(object_dir, _yaw_steps(yaw, part), part)
    return int(np.isfinite(grasps["score"][:, 0]).sum()) >= MIN_GRASP_KEYS


def grasp_reachable(object_dir: str, yaw: float, part: str, position: tuple[float, float]) -> bool:
    """The arm, from its home pose, reaches one of the grasps the oracle tries first on `part` of the object resting
    on the table turned by `yaw` with its origin at `position` (x, y): the best machine.PLAN_CANDIDATES of each of
    GRASP_CHECK_KEYS searches, either closing direction, its via point, pre-pose and pose (machine.approach_reachable).
    A laptop's front edge at the far end of the object range, or a knife pushed 12 cm away from the robot before its
    grasp (types 14 and 16), had none: the oracle found no grasp to try and the episode could not be done."""
    searched_yaw, grasps = _best_grasps(object_dir, _yaw_steps(yaw, part), part)
    turn = yaw_matrix(yaw - searched_yaw)
    shift = np.array([position[0], position[1], 0.0])
    flat = {name: value.reshape(-1, *value.shape[2:]) for name, value in grasps.items()}
    return bool(_any_reachable(_arm(), (flat["centre"] @ turn.T + shift).astype(np.float32),
                               (flat["approach"] @ turn.T).astype(np.float32),
                               (flat["closing"] @ turn.T).astype(np.float32), np.isfinite(flat["score"])))


def air_turn_fits(object_dir: str, yaw: float, position: tuple[float, float], chain, grasp: int) -> bool:
    """For a chain whose grasp at step `grasp` is followed by a turn in the air (before the next release): some grasp
    the oracle tries first on the grasped part of the object resting on the table turned by `yaw` with its origin at
    `position` (x, y) is in the look-ahead's best tier (lookahead.CLEAR_AND_FITS): reached from home
    (machine.approach_reachable), the arm carries out the carries and the turn after it, and the turned object ends
    where the task's AT goal wants it (rotation.TurnPlan.fits). The candidates are the planner's for an air turn
    (machine.candidate_pool with the lever weight), from AIR_TURN_KEYS searches. A kitchen pot held by the knob on its
    lid, its bottom to face the robot, had to be swung round its origin with the hand pointing back at the robot
    (out of reach) or about the hand, 15 cm away from the AT goal; a box held from above and turned upside down ends
    with the hand under it, 16 cm too high. True for any other chain."""
    names = _chain_parts(chain)
    chains = machine.compile_chains([SimpleNamespace(chain=chain)], names)
    kinds, tables = chains["kind"][0], chains["on_table_turn"][0]
    later = np.arange(len(kinds)) > grasp
    held = np.cumsum(later & (kinds == RELEASE)) == 0
    if not (later & held & (kinds == ROTATE) & ~tables).any():
        return True
    geometry = load_object_geometry(object_dir)
    rotation = yaw_matrix(yaw)
    origin = np.array([position[0], position[1], TABLE_HEIGHT - (rotation @ geometry.object_points)[2].min()],
                      np.float32)
    shift = np.array([position[0], position[1], 0.0], np.float32)
    # FACING's vector of each part row (padded to the chain's size, so the check compiles once per cloud size).
    vectors = np.zeros((len(kinds), 3), np.float32)
    for row, name in enumerate(names):
        _, (points, _, valid) = _resting_clouds(object_dir, yaw, name)
        vectors[row] = points[valid].mean(axis=0) + shift - origin
    (points, normals, valid), (part_points, part_normals, part_valid) = _resting_clouds(object_dir, yaw,
                                                                                      chain[grasp].part)
    whole, part = _padded(points + shift, normals, valid), _padded(part_points + shift, part_normals, part_valid)
    chain_arrays = {name: jnp.asarray(chains[name][0]) for name in ("kind", "direction", "put_down", "part",
                                                                    "on_table_turn", "num_skills")}
    # One search after the other, until one has a grasp that fits (most draws that have one have it in the first).
    return any(_best_air_turn_tier(_arm(), *whole, *part, chain_arrays, grasp, origin, vectors, key)
               == lookahead.CLEAR_AND_FITS for key in jax.random.split(jax.random.PRNGKey(0), AIR_TURN_KEYS))


def _chain_parts(chain) -> list[str]:
    """The part names a chain uses, each once (the part rows of its compiled chain)."""
    return list(dict.fromkeys(step.part for step in chain if step.part is not None))


@jax.jit
def _best_air_turn_tier(kinematics, object_points, object_normals, object_valid, part_points, part_normals,
                        part_valid, chain, grasp, object_pos, part_vectors, key):
    """The best look-ahead tier of the reachable grasps of one of `air_turn_fits`' searches (`key`): the planner's
    candidates for an air turn, both closing directions, checked AIR_TURN_CHUNK at a time in rank order until one is
    in the best tier."""
    home = jnp.asarray(HOME_ARM_QPOS, jnp.float32)
    grasps = candidates.grasp_candidates(object_points, object_normals, object_valid, part_points, part_normals,
                                         part_valid, key, lever_weight=machine.AIR_TURN_LEVER_WEIGHT)
    top = machine.candidate_pool(grasps["score"], jnp.abs(grasps["approach"][:, 2]) < machine.LEVEL_APPROACH, True)
    poses = _both_closings(grasps["centre"][top], grasps["approach"][top], grasps["closing"][top],
                           jnp.isfinite(grasps["score"][top]))

    def tier(position, quat, axis, usable):
        reached, joints = machine.approach_reachable(kinematics, home, position, quat, axis)
        outlook = lookahead.outlook(kinematics, joints, position, quat, chain, grasp, object_pos, object_points,
                                    object_valid, lambda row: part_vectors[row])
        return jnp.where(reached & usable, outlook, lookahead.BLOCKED)

    def body(carry):
        i, best = carry
        chunk = [jax.lax.dynamic_slice_in_dim(x, i * AIR_TURN_CHUNK, AIR_TURN_CHUNK) for x in poses]
        return i + 1, jnp.minimum(best, jax.vmap(tier)(*chunk).min())

    def more(carry):
        i, best = carry
        return (i * AIR_TURN_CHUNK < poses[0].shape[0]) & (best != lookahead.CLEAR_AND_FITS)

    return jax.lax.while_loop(more, body, (0, lookahead.BLOCKED))[1]


def _yaw_steps(yaw: float, part: str) -> int | None:
    """The cache key of a part's grasp search: None for a semantic part (searched at yaw 0), else `yaw` in YAW_STEPs."""
    return None if part not in SPATIAL_PARTS else round(yaw / YAW_STEP) % round(2 * math.pi / YAW_STEP)


@functools.lru_cache(maxsize=None)
def _best_grasps(object_dir: str, yaw_steps: int | None, part: str) -> tuple[float, dict[str, np.ndarray]]:
    """The yaw the part was searched at, and per GRASP_CHECK_KEYS key the machine.PLAN_CANDIDATES best grasps on it
    (candidates.grasp_candidates' fields centre, approach, closing, score: (keys, PLAN_CANDIDATES, ...)), in the
    world frame of the object resting on the table with its origin above (0, 0)."""
    yaw = 0.0 if yaw_steps is None else yaw_steps * YAW_STEP
    whole, part = _resting_clouds(object_dir, yaw, part)
    grasps = _best_grasps_per_key(*_padded(*whole), *_padded(*part))
    return yaw, {name: np.asarray(value) for name, value in grasps.items()}


def touch_reachable(object_dir: str, yaw: float, part: str, position: tuple[float, float],
                    push_side: np.ndarray) -> bool:
    """The arm, from its home pose, reaches one of the oracle's touch poses on `part` of the object resting on the
    table turned by `yaw` with its origin at `position` (x, y): candidates.touch_candidates with `push_side` (the side
    a following push comes from, zero without one), machine.touch_poses, machine.approach_reachable. The part's
    box being exposed (the cheap rule) is not enough: two staplers' bodies under their lids, turned, had no touch
    pose the search would use, and the oracle's touch failed (docs/oracle.md)."""
    (points, normals, valid), (part_points, part_normals, part_valid) = _resting_clouds(object_dir, yaw, part)
    shift = np.array([position[0], position[1], 0.0], np.float32)
    padded, padded_part = _padded(points + shift, normals, valid), _padded(part_points + shift, part_normals, part_valid)
    return bool(_any_touch_reachable(_arm(), padded[0], padded[2], padded_part[0], padded_part[2],
                                     np.asarray(push_side, np.float32)))


def _resting_clouds(object_dir: str, yaw: float, part: str):
    """(points, normals, valid) of the whole object (every second point, as the oracle's planners search it) and of
    `part`, in the world frame of the object resting on the table turned by `yaw` with its origin above (0, 0)."""
    geometry = load_object_geometry(object_dir)
    rotation = yaw_matrix(yaw)
    if part in SPATIAL_PARTS:
        points, normals = geometry.object_points, geometry.object_normals
        valid = np.asarray(_spatial_masks((rotation @ points).T))[SPATIAL_PARTS.index(part)]
    else:
        index = geometry.part_names.index(part)
        points, normals = geometry.part_points[index], geometry.part_normals[index]
        valid = np.ones(points.shape[1], bool)
    lift = np.array([0.0, 0.0, TABLE_HEIGHT - (rotation @ geometry.object_points)[2].min()])[:, None]

    def world(p, n, v):
        return (rotation @ p + lift).T.astype(np.float32), (rotation @ n).T.astype(np.float32), np.asarray(v, bool)

    whole = world(geometry.object_points[:, ::2], geometry.object_normals[:, ::2],
                  np.ones(geometry.object_points[:, ::2].shape[1], bool))
    return whole, world(points, normals, valid)


def _padded(points, normals, valid):
    """Points, normals and validity padded (invalid) to a power of two of at least 256 rows, so the jitted search
    compiles for a few shapes, not once per part (slow on a GPU)."""
    size = max(256, 1 << (len(points) - 1).bit_length())
    extra = size - len(points)
    return (np.pad(points, ((0, extra), (0, 0))), np.pad(normals, ((0, extra), (0, 0))),
            np.pad(valid, (0, extra)))


@jax.jit
def _best_grasps_per_key(object_points, object_normals, object_valid, part_points, part_normals, part_valid):
    def best(key):
        grasps = candidates.grasp_candidates(object_points, object_normals, object_valid, part_points, part_normals,
                                             part_valid, key)
        score, top = jax.lax.top_k(grasps["score"], machine.PLAN_CANDIDATES)
        return {"score": score, **{name: grasps[name][top] for name in ("centre", "approach", "closing")}}

    return jax.vmap(best)(jax.random.split(jax.random.PRNGKey(0), GRASP_CHECK_KEYS))


@jax.jit
def _any_touch_reachable(kinematics, object_points, object_valid, part_points, part_valid, push_side):
    """Whether the arm reaches, from home, any usable touch pose on the part (machine._plan_touch's candidates)."""
    points, axes, x_axes, score = candidates.touch_candidates(object_points, object_valid, part_points, part_valid,
                                                              push_side)
    positions, quats = machine.touch_poses(points, axes, x_axes)
    return _any_reached_from_home(kinematics, positions, quats, axes, jnp.isfinite(score))


@functools.lru_cache(maxsize=1)
def _arm() -> jax_ik.ArmKinematics:
    return jax_ik.ArmKinematics.from_scene(build_scene())


@jax.jit
def _any_reachable(kinematics, centres, approaches, closings, valid):
    """Whether the arm reaches, from home, any valid grasp (rows of centre, approach, closing) either way round."""
    return _any_reached_from_home(kinematics, *_both_closings(centres, approaches, closings, valid))


def _both_closings(centres, approaches, closings, valid):
    """TCP positions, quaternions, approach axes and validity of grasps (rows of centre, approach, closing) with
    either closing direction: every grasp as given, then every grasp turned half a turn about its approach."""
    positions, quats_a, quats_b = jax.vmap(candidates.tcp_pose)(centres, approaches, closings)
    return (jnp.tile(positions, (2, 1)), jnp.concatenate([quats_a, quats_b]), jnp.tile(approaches, (2, 1)),
            jnp.tile(valid, 2))


def _any_reached_from_home(kinematics, positions, quats, axes, usable):
    """Whether `machine.approach_reachable` holds from the arm's home pose for any usable pose (rows)."""
    home = jnp.asarray(HOME_ARM_QPOS, jnp.float32)
    reached, _ = jax.vmap(machine.approach_reachable, in_axes=(None, None, 0, 0, 0))(kinematics, home, positions,
                                                                                     quats, axes)
    return (reached & usable).any()


def _view(local: np.ndarray, rotation: np.ndarray, object_world: np.ndarray, resting_rise: np.ndarray) -> PartView:
    world = rotation @ local
    lo, hi = world.min(axis=1), world.max(axis=1)
    free = _reach(lo, hi) + 0.1 * np.linalg.norm(hi - lo) >= _reach_at_level(object_world, lo, hi)
    offset = world.mean(axis=1)
    size = object_world.shape[1]
    padded = np.zeros((size, 3), np.float32)
    padded[: world.shape[1]] = world.T
    ok = np.asarray(_pushable(padded, np.arange(size) < world.shape[1], object_world.T.astype(np.float32)))
    return PartView(offset=offset, facing=nearest_direction(offset),
                    exposed=frozenset(word for word, ok in zip(APPROACHES, free) if ok),
                    pushable=frozenset(word for word, good in zip(HORIZONTAL, ok) if good),
                    put_down_facing=_put_down_facing(local.mean(axis=1), resting_rise))


def _put_down_facing(offset: np.ndarray, resting_rise: np.ndarray) -> frozenset[str]:
    """PartView.put_down_facing of a part whose FACING vector is `offset` (root frame). A yaw leaves the elevation
    of the part's vector as it is, so the part can face a word in some orientation with UP_SAMPLES[k] up when that
    elevation is within FACING_THRESHOLD of the word's."""
    elevation = np.arcsin(np.clip(UP_SAMPLES @ (offset / np.linalg.norm(offset)), -1.0, 1.0))
    low = resting_rise < PUT_DOWN_AT_THRESHOLD
    return frozenset(word for word, d in DIRECTIONS.items()
                     if (low & (np.abs(elevation - math.asin(d[2])) <= FACING_THRESHOLD)).any())


@jax.jit
def _pushable(part_points, part_valid, object_points):
    """Per HORIZONTAL word, whether the part has a push point for a push that way."""
    directions = jnp.asarray([DIRECTIONS[word] for word in HORIZONTAL], jnp.float32)
    valid = jnp.ones(object_points.shape[0], bool)
    return jax.vmap(lambda d: pushing.push_point(part_points, part_valid, object_points, valid, d)[1])(directions)


def _reach(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """How far a box reaches along each approach direction."""
    return np.maximum(_APPROACH_AXES @ lo, _APPROACH_AXES @ hi)


def _reach_at_level(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """How far the object reaches along each approach direction next to the box lo..hi: side approaches among
    points at its height, the top one among points over its footprint (-inf where there are none)."""
    at_height = points[:, (points[2] >= lo[2]) & (points[2] <= hi[2])]
    over = points[:, np.all((points[:2] >= lo[:2, None]) & (points[:2] <= hi[:2, None]), axis=0)]
    reach = np.full(len(APPROACHES), -np.inf)
    for i, (word, axis) in enumerate(zip(APPROACHES, _APPROACH_AXES)):
        near = over if word == "top" else at_height
        if near.shape[1]:
            reach[i] = (axis @ near).max()
    return reach


@functools.lru_cache(maxsize=None)
def part_roles(type_id: int) -> Mapping[str, str]:
    """Part slot -> 'grasp', 'touch' or 'rotate' (the skill that uses it)."""
    return MappingProxyType({step.part: step.name.removesuffix("_obj") for step in task_type(type_id).chain
                             if step.part})


@functools.lru_cache(maxsize=None)
def direction_roles(type_id: int) -> Mapping[str, tuple[str, str | None]]:
    """Direction slot -> (role, part slot it depends on); roles: move, push, rotate_air, rotate_put_down (in the air,
    a put-down follows), rotate_table, opposite."""
    roles, in_air, touched = {}, False, None
    chain = task_type(type_id).chain
    for index, step in enumerate(chain):
        if step.name == "touch_obj":
            touched = step.part
        elif step.name == "grasp_obj":
            in_air = False
        elif step.name == "move_gripper" and step.direction in ("top", "bottom"):
            in_air = step.direction == "top"
        elif step.name == "move_gripper":
            roles[step.direction] = ("push", touched) if step.touching else ("move", None)
        elif step.name == "rotate_obj":
            put_down = any(later.put_down for later in chain[index + 1:])
            role = ("opposite" if type_id in OPPOSITE_TYPES else "rotate_table" if not in_air
                    else "rotate_put_down" if put_down else "rotate_air")
            roles[step.direction] = (role, step.part)
    return MappingProxyType(roles)


def allowed_by_name(role: str, category: str, part: str) -> bool:
    """The rules that depend on the part's name only."""
    if part in CAVITIES or part == "middle":
        return False
    if role == "rotate":
        return True
    return part != "bottom" and (role == "touch" or part not in GRASP_EXCLUDED.get(category, ()))


def fits_role(role: str, view: PartView) -> bool:
    """The rules that depend on the part's geometry at the initial pose."""
    if role == "grasp":
        return bool(view.exposed)
    if role == "touch":
        return bool(view.exposed)
    return float(np.linalg.norm(view.offset)) >= MIN_FACING_OFFSET


def direction_candidates(role: str, view: PartView | None, moves: list[str]) -> list[str]:
    """Valid words for a direction slot of `role` (`view`: the part it depends on; `moves`: workspace_moves)."""
    if role == "move":
        return moves
    if role == "push":
        return [w for w in moves if OPPOSITE[w] in view.exposed and w in view.pushable]
    facing = view.facing
    if role == "rotate_air":
        return [w for w in DIRECTIONS if w != facing]
    if role == "rotate_put_down":
        return [w for w in DIRECTIONS if w != facing and w in view.put_down_facing]
    level = float(np.linalg.norm(view.offset[:2]))
    if (facing not in HORIZONTAL or level < MIN_FACING_OFFSET
            or math.atan2(abs(float(view.offset[2])), level) > MAX_TABLE_TURN_ELEVATION):
        return []
    return [OPPOSITE[facing]] if role == "opposite" else [w for w in HORIZONTAL if w != facing]


def workspace_moves(position: tuple[float, float]) -> list[str]:
    """Horizontal words a unit move can take the object along without leaving WORKSPACE."""
    return [word for word in HORIZONTAL
            if all(lo <= p + UNIT_DISTANCE * d <= hi for p, d, (lo, hi) in zip(position, DIRECTIONS[word], WORKSPACE))]


def feasible_assignments(type_id: int, category: str, views: dict[str, PartView],
                         position: tuple[float, float]) -> list[tuple[dict[str, str], dict[str, list[str]]]]:
    """Every assignment of distinct parts to the type's part slots with, per direction slot, its valid words."""
    roles, direction_slots = part_roles(type_id), direction_roles(type_id)
    choices = {slot: [p for p, v in views.items() if allowed_by_name(role, category, p) and fits_role(role, v)]
               for slot, role in roles.items()}
    moves = workspace_moves(position)
    words = {slot: {part: direction_candidates(role, views.get(part), moves) for part in choices.get(part_slot, [None])}
             for slot, (role, part_slot) in direction_slots.items()}
    assignments = []
    for combo in itertools.product(*choices.values()):
        if len(set(combo)) < len(combo):
            continue
        parts = dict(zip(roles, combo))
        directions = {slot: words[slot][parts.get(part_slot)] for slot, (_, part_slot) in direction_slots.items()}
        if all(directions.values()):
            assignments.append((parts, directions))
    return assignments


def combination(type_id: int, parts: dict[str, str]) -> tuple[str, ...]:
    """The parts a task sentence names, in slot order: what Test 3 recombines."""
    return tuple(parts[slot] for slot in instruction_slots(type_id) if slot in part_roles(type_id))


def held_out_combinations(category: str, type_id: int, semantic_parts) -> frozenset[tuple[str, ...]]:
    """Test 3's part combinations for (category, type): never in train or test1.

    Every combination the name rules allow (the category's semantic parts plus the spatial words) is ranked by the
    CRC-32 of 'category|type|parts'; the first quarter (at least one) is held out. It depends only on the
    category's part vocabulary, not on the seed, so every generated set agrees on it.
    """
    roles = part_roles(type_id)
    named = [slot for slot in instruction_slots(type_id) if slot in roles]
    vocabulary = sorted(set(semantic_parts)) + list(SPATIAL_WORDS)
    choices = [[p for p in vocabulary if allowed_by_name(roles[slot], category, p)] for slot in named]
    combos = [c for c in itertools.product(*choices) if len(set(c)) == len(c)]
    combos.sort(key=lambda c: zlib.crc32(f"{category}|{type_id}|{'|'.join(c)}".encode()))
    return frozenset(combos[:max(1, math.ceil(HELD_OUT_FRACTION * len(combos)))])
