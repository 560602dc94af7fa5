"""Words of the benchmark: directions (world axes, spec 3.1), spatial parts, the unit move distance."""

from __future__ import annotations

import numpy as np

from partinstruct_mjx.errors import TaskError

DIRECTIONS: dict[str, tuple[float, float, float]] = {
    "left": (0.0, 1.0, 0.0),
    "right": (0.0, -1.0, 0.0),
    "front": (-1.0, 0.0, 0.0),
    "back": (1.0, 0.0, 0.0),
    "top": (0.0, 0.0, 1.0),
    "bottom": (0.0, 0.0, -1.0),
}
"""Fixed world axes; they coincide with the static camera's view (left = image left, front = towards it)."""

OPPOSITE = {"left": "right", "right": "left", "front": "back", "back": "front", "top": "bottom", "bottom": "top"}
HORIZONTAL = ("left", "right", "front", "back")

SPATIAL_PARTS = ("left", "right", "front", "back", "top", "bottom", "middle")
"""Parts defined by position on the object (spec 3.3), available for every object."""

UNIT_DISTANCE = 0.12
"""Metres moved by one move_gripper skill (spec 5.1)."""


def direction_vector(word: str) -> np.ndarray:
    """Unit vector of a direction word; raises TaskError naming an unknown word."""
    if word not in DIRECTIONS:
        raise TaskError(f"unknown direction '{word}'; expected one of {', '.join(DIRECTIONS)}")
    return np.array(DIRECTIONS[word])


def nearest_direction(vector: np.ndarray, candidates=tuple(DIRECTIONS)) -> str:
    """The direction word whose axis is closest in angle to `vector`."""
    vector = np.asarray(vector, dtype=float)
    return max(candidates, key=lambda word: float(np.dot(DIRECTIONS[word], vector)))
