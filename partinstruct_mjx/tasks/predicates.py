"""Goal predicates (spec 4) as pure JAX functions of one environment's SceneState rows; vmap them for a batch.

Thresholds are the original's. Where we measure differently (contacts carry the touched geom, so GRASPING uses part
labels instead of a 3 mm point search for semantic parts; fingers touching each other is read from the finger
joints instead of stepping the simulation) docs/differences.md says so. Nothing here advances the simulation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from partinstruct_mjx.control.rotations import quat_rotate
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import TABLE_HEIGHT
from partinstruct_mjx.tasks.part_geometry import PartGeometry, world_points
from partinstruct_mjx.vectors import squared_norm

ON_TABLE_DISTANCE = 0.002
"""ON: the object's lowest surface point within this of the table top (the original: 1 mm between the bodies;
surface samples sit up to ~1 mm above the true lowest point)."""
GRASP_FORCE = 20.0
"""GRASPING: newtons of normal force one finger must press on the object (summed over its contacts)."""
SPATIAL_CONTACT_DISTANCE = 0.006
"""GRASPING a spatial part: a finger contact within this of the region's points (sample spacing is ~4 mm)."""
FINGERS_CLOSED_WIDTH = 0.004
"""TOUCHING: the fingers count as closed onto each other below this pad distance."""
TOUCH_DISTANCE = 0.01
FINGERTIP_OFFSET = 0.05625
"""Fingertip point = TCP + this along the TCP's z axis (spec 1.3)."""
GRIPPER_OPEN_TOLERANCE = 0.005
MIN_TCP_DISTANCE = 0.05
FACING_ANGLE = 0.5


def part_cloud(state, geo: PartGeometry, masks: jnp.ndarray, part: jnp.ndarray):
    """World points (M, 3) and validity (M,) of part row `part` for one environment; `masks` (7, M) are spatial."""
    points = world_points(state.body_pos, state.body_quat, geo.points[part], geo.bodies[part])
    spatial = part - geo.num_semantic
    is_spatial = (spatial >= 0) & (spatial < masks.shape[0])
    mask = jnp.where(is_spatial, masks[jnp.clip(spatial, 0, masks.shape[0] - 1)], True)
    return points, geo.valid[part] & mask


def masked_mean(points: jnp.ndarray, valid: jnp.ndarray) -> jnp.ndarray:
    """Mean (3,) of the valid rows of points (M, 3); zero when none is valid."""
    return (points * valid[:, None]).sum(axis=0) / jnp.maximum(valid.sum(), 1)


def object_points(state, geo: PartGeometry) -> jnp.ndarray:
    """World points of the whole object (M, 3)."""
    return world_points(state.body_pos, state.body_quat, geo.points[geo.whole], geo.bodies[geo.whole])


def on_table(state, geo: PartGeometry) -> jnp.ndarray:
    return object_points(state, geo)[:, 2].min() <= TABLE_HEIGHT + ON_TABLE_DISTANCE


def gripper_open(state) -> jnp.ndarray:
    return jnp.abs(state.finger_qpos[0] - panda.FINGER_OPEN) < GRIPPER_OPEN_TOLERANCE


def min_distance(state) -> jnp.ndarray:
    return jnp.linalg.norm(state.object_pos - state.tcp_pos) > MIN_TCP_DISTANCE


def at_position(state, target: jnp.ndarray, threshold: jnp.ndarray) -> jnp.ndarray:
    return jnp.linalg.norm(state.object_pos - target) < threshold


def facing(state, geo, masks, part, direction: jnp.ndarray, threshold=FACING_ANGLE) -> jnp.ndarray:
    """The vector from the object origin to the part's mean point is within `threshold` rad of `direction`."""
    return points_along(part_vector(state, geo, masks, part), direction, threshold)


def part_vector(state, geo, masks, part) -> jnp.ndarray:
    """(3,) from the object origin to the part's mean point: the vector FACING measures."""
    points, valid = part_cloud(state, geo, masks, part)
    return masked_mean(points, valid) - state.object_pos


def points_along(vector: jnp.ndarray, direction: jnp.ndarray, threshold) -> jnp.ndarray:
    """`vector` is within `threshold` rad of `direction` (FACING's angle test)."""
    cosine = vector @ direction / jnp.maximum(jnp.linalg.norm(vector) * jnp.linalg.norm(direction), 1e-9)
    return jnp.arccos(jnp.clip(cosine, -1.0, 1.0)) < threshold


def grasping(state, geo, masks, part) -> jnp.ndarray:
    """One finger presses the object with > 20 N and touches the part (any part for the whole-object row)."""
    on_object, label = _on_object(state, geo)
    labelled = on_object & (label == part)
    points, valid = part_cloud(state, geo, masks, part)
    near = on_object & (within(state.contact_pos[..., None, :], points, SPATIAL_CONTACT_DISTANCE) & valid).any(axis=-1)
    is_semantic = part < geo.num_semantic
    on_part = jnp.where(part == geo.whole, on_object, jnp.where(is_semantic, labelled, near)).any(axis=-1)
    return (pressing(state, geo) & on_part).any()


def fingertip(state) -> jnp.ndarray:
    """World fingertip point (3,): TCP + FINGERTIP_OFFSET along the TCP's z axis."""
    return state.tcp_pos + quat_rotate(state.tcp_quat, jnp.array([0.0, 0.0, FINGERTIP_OFFSET]))


def fingers_closed(state) -> jnp.ndarray:
    return state.finger_qpos.sum() < FINGERS_CLOSED_WIDTH


def touching(state, geo, masks, part) -> jnp.ndarray:
    """The gripper is closed and its fingertip point is within 1 cm of the part."""
    return touching_points(state, *part_cloud(state, geo, masks, part))


def touching_points(state, points: jnp.ndarray, valid: jnp.ndarray) -> jnp.ndarray:
    """TOUCHING of a part given by its world points (M, 3) and their validity (M,)."""
    return fingers_closed(state) & (within(points, fingertip(state), TOUCH_DISTANCE) & valid).any()


def within(a: jnp.ndarray, b: jnp.ndarray, distance: float) -> jnp.ndarray:
    """Points a and b (broadcast, (..., 3)) lie closer than `distance` (no square root: vectors.py)."""
    return squared_norm(a - b) < distance * distance


def released(state, geo, masks) -> jnp.ndarray:
    """The release effects (spec 5.2): not grasping, not touching, gripper open, gripper away from the object."""
    whole = jnp.asarray(geo.whole)
    return (~grasping(state, geo, masks, whole) & ~touching(state, geo, masks, whole)
            & gripper_open(state) & min_distance(state))


@struct.dataclass
class PartFacts:
    """The part-dependent predicates of one environment for every part row at once (what `grasping`, `touching`
    and `facing` compute one part at a time), plus ON.

    grasped, touched: (K,) GRASPING / TOUCHING of each part row; centers: (K, 3) world mean point of each row's
    (masked) cloud; on_table: ON of the object.
    """

    grasped: jnp.ndarray
    touched: jnp.ndarray
    centers: jnp.ndarray
    on_table: jnp.ndarray


def part_facts(state, geo: PartGeometry, masks: jnp.ndarray) -> PartFacts:
    """`PartFacts` of one environment; each distinct cloud is transformed and searched once."""
    return _facts(state, geo, contact_regions(state, geo, masks), tip_near(state, geo, masks),
                  part_centers(state, geo, masks), on_table(state, geo))


def batch_part_facts(state, geo: PartGeometry, masks: jnp.ndarray, regions=True, tips=True, centers=True,
                     table=True) -> PartFacts:
    """`part_facts` of a batch (leading dimension B), each search run only when its facts can matter (skipped ones
    are false or zero): the contact search when `regions` (a traced bool: some goal row is GRASPING a spatial part)
    and some finger of the batch presses the object, the fingertip search when `tips` (some row is TOUCHING or
    RELEASED) and some gripper is closed (GRASPING and TOUCHING are false otherwise whatever the searches find), the
    part centres when `centers` (some row is FACING), ON when `table` (some row is ON)."""
    batch = masks.shape[0]
    spatial = masks.shape[1]
    rows = geo.points.shape[0]
    pressed = jax.vmap(pressing, in_axes=(0, None))(state, geo).any()
    near_contacts = jax.lax.cond(regions & pressed,
                                 lambda: jax.vmap(contact_regions, in_axes=(0, None, 0))(state, geo, masks),
                                 lambda: jnp.zeros((batch, 2, spatial), bool))
    closed = jax.vmap(fingers_closed)(state).any()
    near_tip = jax.lax.cond(tips & closed, lambda: jax.vmap(tip_near, in_axes=(0, None, 0))(state, geo, masks),
                            lambda: jnp.zeros((batch, rows), bool))
    means = jax.lax.cond(centers, lambda: jax.vmap(part_centers, in_axes=(0, None, 0))(state, geo, masks),
                         lambda: jnp.zeros((batch, rows, 3), geo.points.dtype))
    on = jax.lax.cond(table, lambda: jax.vmap(on_table, in_axes=(0, None))(state, geo),
                      lambda: jnp.zeros(batch, bool))
    return jax.vmap(_facts, in_axes=(0, None, 0, 0, 0, 0))(state, geo, near_contacts, near_tip, means, on)


def _on_object(state, geo: PartGeometry) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(2, C) contacts of each finger that touch the object, and the part row label of each contact's geom."""
    geom = state.contact_geom
    label = geo.geom_part[jnp.maximum(geom, 0)]
    return (geom >= 0) & (label >= 0), label


def finger_on_object(state, geo: PartGeometry) -> jnp.ndarray:
    """A finger has a contact with force on the object (any part)."""
    on_object, _ = _on_object(state, geo)
    return (state.contact_force * on_object).any()


def pressing(state, geo: PartGeometry) -> jnp.ndarray:
    """(2,) each finger presses the object with more than GRASP_FORCE newtons (summed over its contacts)."""
    on_object, _ = _on_object(state, geo)
    return (state.contact_force * on_object).sum(axis=-1) > GRASP_FORCE


def _spatial_rows(geo: PartGeometry, masks: jnp.ndarray) -> jnp.ndarray:
    """(8, M) validity of the object cloud's points for the spatial rows, then the whole object."""
    valid = geo.valid[geo.whole]
    return jnp.concatenate([masks & valid, valid[None]])


def contact_regions(state, geo: PartGeometry, masks: jnp.ndarray) -> jnp.ndarray:
    """(2, 7) per finger: one of its object contacts lies within SPATIAL_CONTACT_DISTANCE of each spatial part."""
    on_object, _ = _on_object(state, geo)
    gap_ok = within(state.contact_pos[..., None, :], object_points(state, geo), SPATIAL_CONTACT_DISTANCE)  # (2, C, M)
    near = (on_object[..., None] & gap_ok).any(axis=1)  # (2, M)
    return (near[:, None] & _spatial_rows(geo, masks)[None, :-1]).any(axis=-1)


def tip_near(state, geo: PartGeometry, masks: jnp.ndarray) -> jnp.ndarray:
    """(K,) the fingertip point is within TOUCH_DISTANCE of each part row (TOUCHING without the closed gripper)."""
    n = geo.num_semantic
    tip = fingertip(state)
    semantic = world_points(state.body_pos, state.body_quat, geo.points[:n], geo.bodies[:n])  # (n, M, 3)
    near_semantic = within(semantic, tip, TOUCH_DISTANCE) & geo.valid[:n]
    near_whole = within(object_points(state, geo), tip, TOUCH_DISTANCE)
    return jnp.concatenate([near_semantic.any(axis=-1), (near_whole & _spatial_rows(geo, masks)).any(axis=-1)])


def part_centers(state, geo: PartGeometry, masks: jnp.ndarray) -> jnp.ndarray:
    """(K, 3) world mean point of each part row's (masked) cloud."""
    n = geo.num_semantic
    semantic = world_points(state.body_pos, state.body_quat, geo.points[:n], geo.bodies[:n])  # (n, M, 3)
    whole = object_points(state, geo)
    semantic_valid = geo.valid[:n].astype(semantic.dtype)
    rows = _spatial_rows(geo, masks).astype(whole.dtype)
    return jnp.concatenate([jnp.einsum("km,kmc->kc", semantic_valid, semantic)
                            / jnp.maximum(semantic_valid.sum(axis=-1), 1)[:, None],
                            (rows @ whole) / jnp.maximum(rows.sum(axis=-1), 1)[:, None]])


def _facts(state, geo: PartGeometry, regions, tips, centers, on) -> PartFacts:
    n = geo.num_semantic
    on_object, label = _on_object(state, geo)
    labelled = (on_object[..., None] & (label[..., None] == jnp.arange(n))).any(axis=1)  # (2, n)
    on_part = jnp.concatenate([labelled, regions, on_object.any(axis=-1)[:, None]], axis=1)  # (2, K)
    return PartFacts(grasped=(pressing(state, geo)[:, None] & on_part).any(axis=0),
                     touched=fingers_closed(state) & tips, centers=centers, on_table=on)
