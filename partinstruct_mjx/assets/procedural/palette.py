"""Plausible plain colours per material family, drawn from the object's random generator."""

from __future__ import annotations

import numpy as np

FAMILIES: dict[str, tuple[tuple[float, float, float], ...]] = {
    "ceramic": ((0.93, 0.92, 0.88), (0.85, 0.80, 0.70), (0.35, 0.50, 0.70), (0.55, 0.70, 0.55), (0.75, 0.25, 0.22),
                (0.15, 0.15, 0.17), (0.95, 0.80, 0.35)),
    "metal": ((0.75, 0.76, 0.78), (0.55, 0.56, 0.58), (0.35, 0.36, 0.38), (0.72, 0.45, 0.30), (0.78, 0.65, 0.35)),
    "plastic": ((0.80, 0.15, 0.15), (0.15, 0.35, 0.75), (0.15, 0.60, 0.30), (0.95, 0.80, 0.15), (0.95, 0.50, 0.10),
                (0.10, 0.10, 0.12), (0.92, 0.92, 0.92), (0.50, 0.25, 0.65), (0.20, 0.65, 0.70)),
    "glass": ((0.30, 0.55, 0.35), (0.45, 0.28, 0.12), (0.70, 0.82, 0.88), (0.20, 0.35, 0.60), (0.85, 0.88, 0.86)),
    "liquid": ((0.30, 0.18, 0.10), (0.60, 0.35, 0.12), (0.55, 0.75, 0.90), (0.95, 0.95, 0.92), (0.95, 0.55, 0.10)),
    "rubber": ((0.10, 0.10, 0.10), (0.25, 0.25, 0.27), (0.75, 0.15, 0.12), (0.15, 0.30, 0.70), (0.95, 0.55, 0.10)),
    "wood": ((0.55, 0.38, 0.22), (0.40, 0.26, 0.14), (0.70, 0.55, 0.38)),
    "screen": ((0.05, 0.06, 0.08), (0.08, 0.10, 0.14)),
}


def colour(rng: np.random.Generator, family: str) -> tuple[float, float, float]:
    """A colour of `family`, lightly jittered, rounded to 4 decimals."""
    if family not in FAMILIES:
        raise ValueError(f"unknown colour family {family!r}; known: {', '.join(FAMILIES)}")
    options = FAMILIES[family]
    base = np.asarray(options[int(rng.integers(len(options)))])
    jittered = np.clip(base + rng.uniform(-0.04, 0.04, 3), 0.0, 1.0)
    return tuple(round(float(c), 4) for c in jittered)
