"""Object-level split membership of the built-in library (spec 9.4).

Test 1 (new poses), Test 3 (new part combinations) and Test 4 (new task types) use the training objects; Test 2
(OI) holds out instances of seen categories and Test 5 (OC) holds out whole categories. Which categories the
original held out is unknown (spec 14), so ours are a documented choice.
"""

from __future__ import annotations

import zlib

import numpy as np

HELD_OUT_CATEGORIES = ("eyeglasses", "kettle", "pliers")
"""Test 5 (OC): categories never seen in training."""

HELD_OUT_INSTANCES = 2
"""Test 2 (OI): instances per seen category held out of training."""

TRAIN_SPLITS = ("train", "test1", "test3", "test4")


def assign_splits(entries: list[dict], seed: int = 0, held_out_categories=HELD_OUT_CATEGORIES,
                  held_out_instances: int = HELD_OUT_INSTANCES) -> list[dict]:
    """Return catalog entries with their `splits` set; the held-out instances are drawn per category from `seed`."""
    by_category: dict[str, list[dict]] = {}
    for entry in entries:
        by_category.setdefault(entry["category"], []).append(entry)
    assigned = []
    for category, members in sorted(by_category.items()):
        members = sorted(members, key=lambda e: e["id"])
        if category in held_out_categories:
            held = set(range(len(members)))
        else:
            rng = np.random.default_rng([seed, zlib.crc32(category.encode())])
            count = min(held_out_instances, len(members) - 1)
            held = set(rng.choice(len(members), size=count, replace=False).tolist())
        for index, entry in enumerate(members):
            splits = ["test5"] if category in held_out_categories else (["test2"] if index in held else list(TRAIN_SPLITS))
            assigned.append({**entry, "splits": splits})
    return assigned
