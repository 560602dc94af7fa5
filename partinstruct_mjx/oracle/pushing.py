"""Where a fingertip can push an object along a direction without tipping it or turning it away.

A push slides the object against table friction (MuJoCo's 0.5 between object and table): pressing at height h
above the table with the object about to slide, the object tips over its leading bottom edge unless
TABLE_FRICTION * h < the horizontal distance from its centre of mass to that edge. A push off the line through the
object's middle turns it. So a push point is a point of the touched part on its face towards the pusher, at least
TIP_CLEARANCE above the table (the closed pads' round tips), close to the line through the middle along the push,
and low enough not to tip the object (with a margin); the lowest such point, nearest that line, is taken. A part
can be pushed there only where the fingertip, coming in, touches it before anything else of the object stops it.
Used by episode generation (can this part be pushed this way?) and by the oracle (where to touch and push).
Pure JAX for one object; numpy inputs are fine.
"""

from __future__ import annotations

import jax.numpy as jnp

from partinstruct_mjx.tasks.predicates import masked_mean

TABLE_FRICTION = 0.5
"""Friction between objects and the table (the scene's table geom and the converter's object geoms)."""
TIP_MARGIN = 0.7
"""Share of the tipping height a push may use."""
TIP_CLEARANCE = 0.009
"""Lowest push point above the table (m): the closed pads' round tips stay off the table."""
FACE_BAND = 0.012
"""Points this close (m) to the part's extreme towards the pusher make up its face."""
CENTRE_BAND = 0.2
"""A push point lies within this share of the footprint's width across the push (at least MIN_CENTRE_BAND) of the
line through the footprint's middle (where table friction acts: pushing beside it turns the object)."""
MIN_CENTRE_BAND = 0.01
MIN_CENTRAL_POINTS = 3
"""Central push points a part needs (a margin: the settled object and its spatial parts differ a little from the
pose the task was drawn for)."""
BASE_BAND = 0.01
"""Object points this close (m) to its lowest point make up its footprint on the table."""
TOUCH_RAY_RADIUS = 0.012
TOUCH_RAY_START = 0.005
TOUCH_RAY_LENGTH = 0.12
"""A touch point is free when no object point lies within TOUCH_RAY_RADIUS (about the closed fingertips' half width)
of the line the fingertip comes in along, from TOUCH_RAY_START to TOUCH_RAY_LENGTH (m) out from the point."""
WAY_TOUCH = 0.008
"""A fingertip stopped this close (m) to the part touches it (TOUCHING's 1 cm less a margin: the object's convex
pieces stand a few millimetres out of its surface points)."""
APPROACH_TILTS = (0.0, 0.8)
"""Tilts (rad, down from horizontal) of the fingertip's ways in to a push point from the pusher's side: one must be
open (`open_way`). A display's screen sunk 1.3 cm inside its frame had its push point on its edge, where only the
frame around it could be pushed and TOUCHING the screen never held."""


def push_point(part_points, part_valid, object_points, object_valid, direction):
    """The push point (3,) on the part for a push along the horizontal unit `direction`, and whether it is usable
    (enough central points, and a way in to it clear of the object).

    Points are world-frame (M, 3) with validity masks (M,).
    """
    flat = jnp.array([1.0, 1.0, 0.0])
    direction = direction * flat
    bottom, base = _footprint(object_points, object_valid)
    centre = masked_mean(object_points, base)
    # Distance from the centre (of mass, near the footprint's) to the leading bottom edge; the footprint's width.
    lead = jnp.where(base, (object_points - centre) @ direction, -jnp.inf).max()
    across = jnp.cross(jnp.array([0.0, 0.0, 1.0]), direction)
    side = jnp.where(base, object_points @ across, jnp.nan)
    width = jnp.nanmax(side) - jnp.nanmin(side)
    tip_height = TIP_MARGIN * lead / TABLE_FRICTION
    height = part_points[:, 2] - bottom
    lateral = jnp.abs((part_points - centre) @ across)
    usable = face(part_points, part_valid, -direction) & (height >= TIP_CLEARANCE) & (height <= tip_height)
    central = usable & (lateral <= jnp.maximum(MIN_CENTRE_BAND, CENTRE_BAND * width))
    # The point is the lowest, most central usable one even when none is central enough (the object may have
    # turned a little since the task was drawn); whether one is, is what the slot rules ask.
    best = jnp.argmin(jnp.where(usable, height + 2.0 * lateral, jnp.inf))
    point = part_points[best]
    ways_in = [-jnp.cos(t) * direction + jnp.sin(t) * jnp.array([0.0, 0.0, 1.0]) for t in APPROACH_TILTS]
    way_open = jnp.stack([open_way(point, ray, part_points, part_valid, object_points, object_valid)
                          for ray in ways_in]).any()
    return point, (central.sum() >= MIN_CENTRAL_POINTS) & way_open


def open_way(point, ray, part_points, part_valid, object_points, object_valid):
    """Whether the fingertip, coming in to `point` of the part along the unit `ray` out of it, touches the part where
    the object stops it: the first object point it meets (the farthest out within TOUCH_RAY_RADIUS of its way, up to
    TOUCH_RAY_LENGTH) lies within WAY_TOUCH of the part.

    A laptop's screen sits in its frame, which stands about 1 cm further out at its edges; the screen leaning out at
    its top put the frame's edge level with the screen's own face, and the pads met the frame 1.2-1.4 cm before the
    fingertip reached the screen: the laptop slid and TOUCHING never held."""
    offset = object_points - point
    along = offset @ ray
    lateral = jnp.sum(offset ** 2, -1) - along ** 2
    in_way = object_valid & (lateral < TOUCH_RAY_RADIUS ** 2) & (along < TOUCH_RAY_LENGTH)
    stop = point + jnp.where(in_way, along, 0.0).max(initial=0.0) * ray
    return (part_valid & (jnp.sum((part_points - stop) ** 2, -1) < WAY_TOUCH ** 2)).any()


def clear_rays(points, ray, object_points, object_valid, start=TOUCH_RAY_START):
    """(M,) whether the ray from each point along the unit `ray` is clear of the object: no object point lies within
    TOUCH_RAY_RADIUS of it between `start` (default TOUCH_RAY_START, past the point's own surface) and
    TOUCH_RAY_LENGTH."""
    along = object_points @ ray - (points @ ray)[:, None]
    squared = (jnp.sum(object_points ** 2, -1)[None] + jnp.sum(points ** 2, -1)[:, None]
               - 2.0 * points @ object_points.T)
    lateral = squared - along ** 2
    blocked = (object_valid[None] & (along > start) & (along < TOUCH_RAY_LENGTH)
               & (lateral < TOUCH_RAY_RADIUS ** 2))
    return ~blocked.any(axis=1)


def face(points, valid, toward):
    """(M,) the valid points within FACE_BAND of the farthest valid one along `toward`: the face on that side."""
    reach = jnp.where(valid, points @ toward, -jnp.inf)
    return valid & (reach > reach.max() - FACE_BAND)


def footprint_centre(object_points, object_valid):
    """Middle (3,) of the points the object rests on (within BASE_BAND of its lowest point), at their height."""
    return masked_mean(object_points, _footprint(object_points, object_valid)[1])


def _footprint(object_points, object_valid):
    """The object's lowest z and the mask (M,) of its points within BASE_BAND of it."""
    bottom = jnp.where(object_valid, object_points[:, 2], jnp.inf).min()
    return bottom, object_valid & (object_points[:, 2] < bottom + BASE_BAND)

