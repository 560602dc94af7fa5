"""Part-aware grasp and touch poses from part point clouds, pure JAX for one environment (vmap for a batch).

Grasps are antipodal-style candidates: the gripper's closing region (between the open pads) must hold object points,
the open pads and the hand must be free of object points along the whole approach, and the fingers must stay above
the table. Candidates are ranked by how much of what the pads close on is the target part, how well centred the
grasp is on the part, and how top-down the approach is; the arm's reach is checked with the batched IK afterwards.
Touch poses follow spec 8.5: the fingertip comes from the free side that best matches the part's offset (or from
the side opposite a following push).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.control.rotations import matrix_to_quat
from partinstruct_mjx.oracle import pushing as pushing_module
from partinstruct_mjx.sim.panda import FINGER_OPEN
from partinstruct_mjx.sim.scene import TABLE_HEIGHT
from partinstruct_mjx.tasks.predicates import FINGERTIP_OFFSET, masked_mean
from partinstruct_mjx.vectors import dot3, norm3

PAD_CENTRE = 0.0394
"""Distance from the TCP along its z axis to the middle of the finger pads (hand frame z 0.0944 vs 0.055)."""
PAD_HALF_WIDTH = 0.0125
PAD_HALF_LENGTH = 0.017
PAD_THICKNESS = 0.018
"""Depth of a finger pad across the closing axis: an open pad fills [opening, opening + this] from the centre."""
MAX_GRASP_WIDTH = 0.074
"""Widest object section the 8 cm opening closes on (3 mm clearance on both sides)."""
PAD_INNER_MARGIN = 0.002
"""No object point may lie within this of an open pad's inner face."""
OPEN_MARGIN = 0.01
SECTION_GAP = 0.008
SECTION_STEPS = 6
"""A seed's thin-wall grasp pre-shapes the hand: each pad opens OPEN_MARGIN (m) beyond the section it pinches, so
a pad fits between a handle's bar and the wall behind it. The section is the points along the closing axis that
follow each other with gaps under SECTION_GAP (the clouds' spacing is about 4 mm), grown SECTION_STEPS times from
the grasp line; what lies beyond a larger gap (the wall behind an ear) is left outside the pads."""
LOW_GRASP_HEIGHT = 0.03
LOW_GRASP_MARGIN = 0.005
"""A pre-shaped grasp whose pads' middle is under LOW_GRASP_HEIGHT above the table (the edge of a knife or a pair
of scissors lying flat) opens only LOW_GRASP_MARGIN past the section: the first pad to arrive pushes the flat
object aside for as long as the fingers take to close (a device A/B, both margins everywhere: of 100 knife and
scissors episodes 1 cm lost 5 air turns that 5 mm held; of 50 buckets 5 mm lost 4 rim grasps, high above the
table, that 1 cm held)."""
HAND_BACK = 0.028
"""The hand capsule starts this far behind the pads' middle (along the approach, plus margin)."""
HAND_RADIUS = 0.028
"""Radius of the hand's collision capsule (across the fingers' closing axis)."""
HAND_HALF_WIDTH = 0.032
HAND_HALF_LENGTH = 0.12
TABLE_CLEARANCE = 0.002
TIP_CLEARANCE = 0.003
"""Free space the open pads' tips keep from the table and from the object surface ahead of them."""
MIN_DEPTH = 0.01
MAX_DEPTH = 0.025
"""The pads' middle goes this far past the first surface along the approach at least and at most (the palm is
3.1 cm behind it); between the two it sits in the middle of the section along the approach, so that the pads
close across the widest chord of a round part instead of pinching near its edge."""
PREGRASP_DISTANCE = 0.08
LINE_RADIUS = 0.008
CONTACT_BAND = 0.004
"""Points this close to either end of the closed-on section are where a pad lands."""
PART_LANDING = 0.002
"""The target part must reach this close (m) to an end of the closed-on section, where a pad lands first: a
stapler's body under its wider lid, or a box's body under an overhanging lid, is out of the pads' reach."""
MIN_ANTIPODAL = 0.9
"""Smallest mean cosine between the landing surfaces' normals and the pads' pushing directions (26 degrees of tilt:
a squeeze on a more tilted surface pushes the part out of the pads)."""
PARALLEL_FACE = 0.3
"""Surface points whose normal's cosine with the closing axis is below this are left out of the antipodal test."""
TOP_DOWN_WEIGHT = 0.4
"""Score per unit of the approach pointing down (a yaw turn on the table needs the hand above the object: the
planner raises it for those chains)."""
OFF_CENTRE_WEIGHT = 10.0
"""Score lost per metre between the grasp and the object's middle (horizontally)."""

NUM_AZIMUTHS = 8
NUM_SEEDS = 24
SEED_INSET = 0.008
"""The grasp line starts this far inside the surface under the seed (the recentring then finds the section)."""
SIDE_SEED_BIAS = 0.25
"""Seeds are drawn with weight SIDE_SEED_BIAS + the horizontal length of their normal."""
MIN_APPROACH_COMPONENT = 0.5
"""An approach direction is used only if this much of it is left across the seed's normal."""


def _approach_directions() -> np.ndarray:
    """Top-down, horizontal and 45-degree-down approach directions (unit vectors the gripper moves along)."""
    out = [(0.0, 0.0, -1.0)]
    for k in range(NUM_AZIMUTHS):
        c, s = math.cos(2 * math.pi * k / NUM_AZIMUTHS), math.sin(2 * math.pi * k / NUM_AZIMUTHS)
        out += [(c, s, 0.0), (c * math.sqrt(0.5), s * math.sqrt(0.5), -math.sqrt(0.5))]
    return np.array(out)


APPROACHES = _approach_directions().astype(np.float32)


def tcp_quat(approach: jnp.ndarray, closing: jnp.ndarray) -> jnp.ndarray:
    """TCP orientation (w, x, y, z) with z along the approach and y along the fingers' closing axis."""
    x = jnp.cross(closing, approach)
    return matrix_to_quat(jnp.stack([x, closing, approach], axis=-1))


def tcp_pose(centre: jnp.ndarray, approach: jnp.ndarray, closing: jnp.ndarray):
    """TCP position of a grasp whose pads' middle lands at `centre`, and its two orientations (closing along
    `closing`, or the hand turned half a turn about its axis)."""
    return centre - PAD_CENTRE * approach, tcp_quat(approach, closing), tcp_quat(approach, -closing)


def grasp_candidates(object_points, object_normals, object_valid, part_points, part_normals, part_valid, key,
                     num_seeds: int = NUM_SEEDS, top_down_weight=TOP_DOWN_WEIGHT,
                     lever_weight=0.0) -> dict[str, jnp.ndarray]:
    """Scored grasps for one environment: centre (N, 3), approach (N, 3), closing (N, 3), opening (N,) (each
    finger's opening on the approach), score (N,), -inf invalid, and checks (N, 7): something between the pads,
    narrow enough, pads free, hand free, above the table, the part under a pad, antipodal (GRASP_CHECKS).

    Antipodal sampling: a pad lands on a seed point of the part and closes along its normal; the approach is each
    of APPROACHES made perpendicular to that normal. Points (M, 3) are world-frame with outward unit normals.
    lever_weight: score lost per metre between the object's middle and the closing axis through the grasp (the lever
    of the weight's torque about the pinch, which only the pads' torsional friction holds once the object tilts).
    """
    # Half the seeds cover the part evenly (farthest-point sampling: a small knob on a wide lid gets its own), half
    # are drawn favouring side faces (flat parts lying on the table are pinched across them, from above).
    weights = part_valid * (SIDE_SEED_BIAS + jnp.linalg.norm(part_normals[:, :2], axis=-1))
    probabilities = weights / jnp.maximum(weights.sum(), 1e-9)
    drawn_key, start_key = jax.random.split(key)
    drawn = jax.random.choice(drawn_key, part_points.shape[0], (num_seeds - num_seeds // 2,), p=probabilities)
    start = jax.random.choice(start_key, part_points.shape[0], p=probabilities)
    picked = jnp.concatenate([_spread(part_points, part_valid, start, num_seeds // 2), drawn])
    seeds, normals = part_points[picked], part_normals[picked]
    part_centre = masked_mean(part_points, part_valid)
    object_centre = masked_mean(object_points, object_valid)
    extent = jnp.linalg.norm(jnp.where(part_valid[:, None], part_points, part_centre).max(0)
                             - jnp.where(part_valid[:, None], part_points, part_centre).min(0))

    def one(seed, normal, approach, through):
        approach = approach - (approach @ normal) * normal
        length = jnp.linalg.norm(approach)
        approach = approach / jnp.maximum(length, 1e-9)
        # A thin wall is pinched just inside the seed; a solid section across its whole thickness along the normal.
        inset = jnp.where(through, 0.5 * _thickness(seed, normal, object_points, object_valid), SEED_INSET)
        inner = seed - inset * normal
        first, last = _section(inner, approach, object_points, object_valid)
        depth = jnp.clip(0.5 * (first + last), first + MIN_DEPTH, first + MAX_DEPTH)
        centre, opening, score, checks = _score(inner + depth * approach, approach, normal, ~through, object_points,
                                                object_normals, object_valid, part_points, part_valid, part_centre,
                                                extent, object_centre, top_down_weight, lever_weight)
        return centre, approach, opening, jnp.where(length > MIN_APPROACH_COMPONENT, score, -jnp.inf), checks

    per_seed = 2 * APPROACHES.shape[0]
    seed_index = jnp.repeat(jnp.arange(num_seeds), per_seed)
    base = jnp.tile(jnp.asarray(np.concatenate([APPROACHES, APPROACHES])), (num_seeds, 1))
    through = jnp.tile(jnp.arange(per_seed) >= APPROACHES.shape[0], num_seeds)
    centre, approach, opening, score, checks = jax.vmap(one)(seeds[seed_index], normals[seed_index], base, through)
    return {"centre": centre, "approach": approach, "closing": normals[seed_index], "opening": opening,
            "score": score, "checks": checks}


GRASP_CHECKS = ("between", "width", "pads_free", "hand_free", "above_table", "on_part", "antipodal")


def _spread(points, valid, start, count: int) -> jnp.ndarray:
    """Indices (count,) of points spread over the valid ones by farthest-point sampling from `start`."""
    points = jnp.asarray(points)

    def pick(i, state):
        chosen, distance = state
        distance = jnp.minimum(distance, jnp.linalg.norm(points - points[chosen[i - 1]], axis=-1))
        return chosen.at[i].set(jnp.argmax(jnp.where(valid, distance, -1.0))), distance

    chosen = jnp.zeros(count, jnp.int32).at[0].set(start)
    return jax.lax.fori_loop(1, count, pick, (chosen, jnp.full(points.shape[0], jnp.inf)))[0]


def _thickness(seed, normal, object_points, object_valid):
    """How deep the object goes behind `seed` along -normal (within the gripper's reach), metres."""
    d = object_points - seed
    s = -dot3(d, normal)
    off_line = norm3(d + s[:, None] * normal)
    hit = object_valid & (off_line < LINE_RADIUS) & (s > 0) & (s < MAX_GRASP_WIDTH)
    return jnp.where(hit, s, 0.0).max()


def _section(point, approach, object_points, object_valid):
    """Where the line through `point` along the approach enters and leaves the object (distances along it; the
    fingers arrive at the first); both 0 when it misses."""
    d = object_points - point
    t = dot3(d, approach)
    off_line = norm3(d - t[:, None] * approach)
    hit = object_valid & (off_line < LINE_RADIUS)
    first = jnp.where(hit, t, jnp.inf).min()
    last = jnp.where(hit, t, -jnp.inf).max()
    return jnp.where(hit.any(), first, 0.0), jnp.where(hit.any(), last, 0.0)


def _pad_corners(centre, approach, closing, across, opening):
    """World z of the open pads' tips (4) and of the hand's lower corners (4) for a grasp centred at `centre`."""
    signs = jnp.array([[su, sv] for su in (-1, 1) for sv in (-1, 1)], jnp.float32)
    tips = jnp.stack([signs[:, 0] * PAD_HALF_WIDTH, signs[:, 1] * (opening + PAD_THICKNESS),
                      jnp.full(4, PAD_HALF_LENGTH)], axis=1)
    hand = jnp.stack([signs[:, 0] * HAND_HALF_WIDTH, signs[:, 1] * 0.085, jnp.full(4, -HAND_BACK - 0.028)], axis=1)
    return centre[2] + jnp.concatenate([tips, hand]) @ jnp.stack([across[2], closing[2], approach[2]])


def _table_back_off(centre, approach, closing, across, opening):
    """Metres a downward grasp at `centre` backs off along its approach so the open pads' tips clear the table."""
    tips = _pad_corners(centre, approach, closing, across, opening)[:4]
    deficit = TABLE_HEIGHT + TABLE_CLEARANCE + 0.001 - tips.min()
    downward = approach[2] < -MIN_APPROACH_COMPONENT
    return jnp.where(downward & (deficit > 0), deficit / jnp.maximum(-approach[2], 1e-3), 0.0)


def _clear_pad_tips(centre, approach, closing, across, opening, object_points, object_valid):
    """The grasp centre backed off along the approach until the open pads' tips stop short of the table (downward
    grasps of flat parts) and of the object surface ahead of them (a lid's knob over the lid): what is left
    between the pads is what they pinch (at most PAD_HALF_LENGTH of back-off for the surface)."""
    table = _table_back_off(centre, approach, closing, across, opening)
    d = object_points - centre
    u, v, t = dot3(d, across), dot3(d, closing), dot3(d, approach)
    ahead = (object_valid & (jnp.abs(u) < PAD_HALF_WIDTH + 0.003) & (jnp.abs(v) > opening - PAD_INNER_MARGIN - 0.005)
             & (jnp.abs(v) < opening + PAD_THICKNESS) & (t > 0))
    surface = jnp.maximum(PAD_HALF_LENGTH + TIP_CLEARANCE + 0.001 - jnp.where(ahead, t, jnp.inf).min(), 0.0)
    return centre - jnp.maximum(table, jnp.minimum(surface, PAD_HALF_LENGTH)) * approach


def _grown_section(v, slab):
    """(low, high) along the closing axis of the run of `slab` points around v = 0 with gaps under SECTION_GAP."""
    def grow(_, bounds):
        near = slab & (v > bounds[0] - SECTION_GAP) & (v < bounds[1] + SECTION_GAP)
        return jnp.where(near, v, jnp.inf).min(), jnp.where(near, v, -jnp.inf).max()

    return jax.lax.fori_loop(0, SECTION_STEPS, grow, (jnp.float32(0.0), jnp.float32(0.0)))


def _score(centre, approach, closing, pre_shaped, object_points, object_normals, object_valid, part_points,
           part_valid, part_centre, extent, object_centre, top_down_weight, lever_weight):
    across = jnp.cross(closing, approach)

    def local(points, at):
        d = points - at
        return dot3(d, across), dot3(d, closing), dot3(d, approach)

    def facing_pads(u, t):
        """Points level with the pads' faces (across and along the approach); what lies between the pads of these
        depends on the opening."""
        return (jnp.abs(u) < PAD_HALF_WIDTH) & (jnp.abs(t) < PAD_HALF_LENGTH)

    def section(at):
        """Shift along the closing axis that centres the pinched section, and the fingers' opening for it."""
        u, v, t = local(object_points, at)
        slab = object_valid & facing_pads(u, t)
        wide = slab & (jnp.abs(v) < FINGER_OPEN)
        grown = _grown_section(v, slab)
        low = jnp.where(pre_shaped, grown[0], jnp.where(wide, v, jnp.inf).min())
        high = jnp.where(pre_shaped, grown[1], jnp.where(wide, v, -jnp.inf).max())
        found = low <= high
        opening = jnp.where(pre_shaped & found, jnp.minimum(0.5 * (high - low) + OPEN_MARGIN, FINGER_OPEN),
                            FINGER_OPEN)
        return jnp.where(found, 0.5 * (low + high), 0.0), opening

    _, opening = section(centre)
    centre = _clear_pad_tips(centre, approach, closing, across, opening, object_points, object_valid)
    shift, opening = section(centre)
    centre = centre + shift * closing
    # Re-centring along a closing axis that is not level moves the pads' tips up or down: clear the table again.
    centre = centre - _table_back_off(centre, approach, closing, across, opening) * approach
    u, v, t = local(object_points, centre)
    between = object_valid & facing_pads(u, t) & (jnp.abs(v) < opening)
    v_min, v_max = jnp.where(between, v, jnp.inf).min(), jnp.where(between, v, -jnp.inf).max()
    width = v_max - v_min
    # Antipodal: where each pad lands the surface faces that pad. The net push of a pad is along the mean normal of
    # the front faces in its landing band: its cosine with the closing axis is the contact's tilt (a surface curving
    # away on both sides of the pad, like a mug's wall, pushes straight; an off-centre chord of a round part pushes
    # it out along the approach). Faces parallel to the closing axis (the top and bottom of a flat part) and back
    # faces (the inside of a thin wall, behind the face the pad touches) are left out.
    along = dot3(object_normals, closing)
    side_max = between & (along > PARALLEL_FACE) & (v > v_max - CONTACT_BAND)
    side_min = between & (along < -PARALLEL_FACE) & (v < v_min + CONTACT_BAND)

    def net_cosine(side):
        push = side.astype(object_normals.dtype) @ object_normals  # a matrix product once vmapped: fast on a CPU
        return jnp.abs(push @ closing) / jnp.maximum(jnp.linalg.norm(push), 1e-9)

    antipodal = jnp.minimum(net_cosine(side_max), net_cosine(side_min))
    low = centre[2] < TABLE_HEIGHT + LOW_GRASP_HEIGHT
    opening = jnp.where(pre_shaped & low, jnp.minimum(0.5 * width + LOW_GRASP_MARGIN, opening), opening)
    pads = (object_valid & (jnp.abs(u) < PAD_HALF_WIDTH + 0.003) & (t < PAD_HALF_LENGTH + TIP_CLEARANCE)
            & (t > -PREGRASP_DISTANCE - PAD_HALF_LENGTH - 0.01)
            & (jnp.abs(v) > opening - PAD_INNER_MARGIN) & (jnp.abs(v) < opening + PAD_THICKNESS))
    hand = (object_valid & (t < -HAND_BACK) & (t > -HAND_BACK - PREGRASP_DISTANCE - 0.06)
            & (jnp.abs(u) < HAND_HALF_WIDTH) & (jnp.abs(v) < HAND_HALF_LENGTH))
    above_table = _pad_corners(centre, approach, closing, across, opening).min() > TABLE_HEIGHT + TABLE_CLEARANCE

    pu, pv, pt = local(part_points, centre)
    on_part = part_valid & facing_pads(pu, pt) & (jnp.abs(pv) < opening)
    near_pad = on_part & ((pv > v_max - PART_LANDING) | (pv < v_min + PART_LANDING))
    n_between = between.sum()
    target_share = jnp.minimum(on_part.sum() / jnp.maximum(n_between, 1), 1.0)
    checks = jnp.stack([n_between >= 4, width < MAX_GRASP_WIDTH, ~pads.any(), ~hand.any(), above_table,
                        near_pad.sum() >= 2, antipodal > MIN_ANTIPODAL])
    valid = checks.all()
    # Grasps far from the object's middle let it pivot or squeeze out when lifted.
    off_centre = jnp.linalg.norm((centre - object_centre)[:2])
    to_middle = object_centre - centre
    lever = jnp.linalg.norm(to_middle - (to_middle @ closing) * closing)
    score = (0.3 * target_share + 2.0 * antipodal + top_down_weight * (-approach[2])
             - 1.0 * jnp.linalg.norm(centre - part_centre) / jnp.maximum(extent, 0.02)
             - OFF_CENTRE_WEIGHT * off_centre - lever_weight * lever + 0.2 * jnp.minimum(n_between / 20.0, 1.0))
    return centre, opening, jnp.where(valid, score, -jnp.inf), checks


TOUCH_SIDES = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
                       np.float32)
"""Sides the fingertip comes from (left, right, front, back, top; spec 8.5): the TCP's z axis points against them."""
TOUCH_TILTS = (0.0, 0.8, 1.2)
"""Radians the hand is tilted down from horizontal for a side touch: the far (front) side is out of the arm's reach
with a level hand, and low points need the tilt to keep the hand off the table."""
TOP_TOUCH_YAWS = (0.0, 0.5 * np.pi, -0.5 * np.pi)
"""Turns (rad) of the hand about the vertical for a top touch, one in each of TOUCH_TILTS' slots: the closed hand is
23 cm wide along the fingers' closing axis, and coming down on a laptop's keyboard across its open lid it met the
lid; turned a quarter, it comes down beside it."""
TOP_X = np.array([-1.0, 0.0, 0.0], np.float32)
"""The TCP's x axis for a top-down touch, unturned (spec 8.5; yaw 0 of TOP_TOUCH_YAWS, turned by `top_x` below)."""
TOUCH_DEPTH = 0.004
"""How far past the touch point the fingertip is aimed (the touch skill stops as soon as TOUCHING holds)."""
TOUCH_POINTS = 256
"""Part points (evenly strided) a touch chooses from."""
MIN_TOUCH_HEIGHT = 0.02
"""Lowest touch point above the table (m): the closed fingertips are about 2.5 cm wide."""
LOW_TOUCH_HEIGHT = 0.10
"""Touch points below this world z are not touched with a level hand (the hand would hit the table)."""
HAND_BLOCKED_COST = 0.5
"""Score a touch (other than at a push point) loses when the hand (behind the closed fingers) would meet the object
on its way in: a hand tilted down onto a display's 'right' met the screen's top edge and tipped the display over
before the fingertip got there. Such touches still rank after the clear ones (the part may have no other)."""


def touch_candidates(object_points, object_valid, part_points, part_valid, push_side):
    """Fingertip targets per side and tilt (for the top: per TOP_TOUCH_YAWS): point (N, 3), tcp z axis (N, 3), tcp x
    axis (N, 3), score (N,), -inf where not usable.

    push_side (3,): the side a following push comes from (zero when no push follows); it ranks first.
    """
    part_centre = masked_mean(part_points, part_valid)
    object_centre = masked_mean(object_points, object_valid)
    stride = max(1, part_points.shape[0] // TOUCH_POINTS)
    points, valid = part_points[::stride], part_valid[::stride]

    def one(side, tilt, yaw):
        is_top = side[2] > 0.5
        z_axis = jnp.where(is_top, -side, -jnp.cos(tilt) * side - jnp.sin(tilt) * jnp.array([0.0, 0.0, 1.0]))
        top_x = jnp.stack([-jnp.cos(yaw), -jnp.sin(yaw), 0.0])
        # Points the fingertip can come to along its axis without the object in the way, high enough for the hand
        # (below); of those, the ones within pushing.FACE_BAND of the farthest out towards the side (the part's face
        # on that side, or what is open of it): a display's stand plate, low and farthest out, hid its screen's side.
        high = is_top | _side_touch_clears_table(points[:, 2], tilt)
        clear = pushing_module.clear_rays(points, -z_axis, object_points, object_valid)
        free = pushing_module.face(points, valid & high & clear, side)
        # Before a push the fingertip goes where the push will press (pushing.py: low, near the object's middle, on
        # the face towards the pusher); other touches take the free point nearest the part's centre, of those whose
        # hand comes in clear of the object first.
        pushing = (side @ push_side) > 0.5
        blocked = jax.vmap(touch_hand_blocked, in_axes=(0, None, None, None, None))(points, z_axis, top_x,
                                                                                    object_points, object_valid)
        cost = jnp.where(free, jnp.linalg.norm(points - part_centre, axis=-1) + HAND_BLOCKED_COST * blocked, jnp.inf)
        push_at, push_ok = pushing_module.push_point(part_points, part_valid, object_points, object_valid, -side)
        best = jnp.argmin(cost)
        point = jnp.where(pushing, push_at, points[best])
        # (A push point's touches keep their order: the box is loose, and a bucket's push point under its rim was
        # touched with the steeper hand after the flatter one missed.)
        hand_blocked = ~pushing & blocked[best]
        reachable = jnp.where(pushing, push_ok, free.any())
        # Side touches keep the closed fingers off the table (a push point is high enough for a tilted hand); a top
        # touch reaches any part from above.
        above_table = is_top | (pushing & (tilt > 0)) | _side_touch_clears_table(point[2], tilt)
        alignment = (part_centre - object_centre) @ side
        # Before a push the side opposite the push direction comes first (the push can start from there).
        # (A top touch's turned hands rank after the unturned one, as tilted hands after level ones.)
        score = (alignment - 0.01 * (tilt + jnp.abs(yaw)) + jnp.where(pushing, 1.0, 0.0)
                 - jnp.where(hand_blocked, HAND_BLOCKED_COST, 0.0))
        return point, z_axis, touch_axes(z_axis, top_x)[0], jnp.where(reachable & above_table, score, -jnp.inf)

    sides = jnp.repeat(jnp.asarray(TOUCH_SIDES), len(TOUCH_TILTS), axis=0)
    is_top = sides[:, 2] > 0.5
    tilts = jnp.where(is_top, 0.0, jnp.tile(jnp.asarray(TOUCH_TILTS), TOUCH_SIDES.shape[0]))
    yaws = jnp.where(is_top, jnp.tile(jnp.asarray(TOP_TOUCH_YAWS), TOUCH_SIDES.shape[0]), 0.0)
    return jax.vmap(one)(sides, tilts, yaws)


def _side_touch_clears_table(height, tilt):
    """Whether a side touch at world `height` with the hand tilted down by `tilt` keeps the closed fingertips
    (MIN_TOUCH_HEIGHT) and, for a level hand, the hand (LOW_TOUCH_HEIGHT) off the table."""
    return (height > TABLE_HEIGHT + MIN_TOUCH_HEIGHT) & ((height > LOW_TOUCH_HEIGHT) | (tilt > 0))


def touch_hand_blocked(point, z_axis, top_x, object_points, object_valid):
    """Whether an object point lies in the box the hand (behind the closed fingers: HAND_BACK behind the pads'
    middle, HAND_HALF_WIDTH by HAND_HALF_LENGTH) sweeps on its way in along `z_axis` (from PREGRASP_DISTANCE and more
    back) to the touch pose whose fingertip presses `point` (machine.touch_poses, touch_quat's axes)."""
    x_axis, y_axis, _ = touch_axes(z_axis, top_x)
    pads = point - (FINGERTIP_OFFSET - TOUCH_DEPTH - PAD_CENTRE) * z_axis
    d = object_points - pads
    t, u, v = dot3(d, z_axis), dot3(d, x_axis), dot3(d, y_axis)
    inside = ((t < -HAND_BACK) & (t > -HAND_BACK - PREGRASP_DISTANCE - 0.06) & (jnp.abs(u) < HAND_HALF_WIDTH)
              & (jnp.abs(v) < HAND_HALF_LENGTH))
    return (object_valid & inside).any()


def touch_axes(z_axis: jnp.ndarray, top_x=TOP_X) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """The TCP's axes (x, y, z) for a touch: z along `z_axis`, x pointing as far down as possible (the spec's
    side-approach frame) or, for a top-down touch, along the horizontal `top_x` (the spec's: -x world)."""
    down = jnp.array([0.0, 0.0, -1.0])
    x = down - (down @ z_axis) * z_axis
    x = jnp.where(jnp.linalg.norm(x) < 1e-3, jnp.asarray(top_x, jnp.float32), x)
    x = x / jnp.linalg.norm(x)
    return x, jnp.cross(z_axis, x), z_axis


def touch_quat(z_axis: jnp.ndarray, top_x=TOP_X) -> jnp.ndarray:
    """TCP orientation for a touch (touch_axes)."""
    return matrix_to_quat(jnp.stack(touch_axes(z_axis, top_x), axis=-1))
