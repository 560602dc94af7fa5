"""Episodes: the original's metadata JSON (spec 9.2), its validation, and seeded generation for every split.

File schema: {obj_class: {split: {"<type>": [{obj_id, ep_id, chain_params, task_instruction, skill_instructions,
obj_pose [qx, qy, qz, qw, x, y, z], obj_scale, seed}]}}}. `seed` is ours (the per-episode seed everything was
drawn from); readers of the original ignore it and the original's files lack it.

Splits (spec 9.4, object membership from the catalog): train, test1 (new poses), test3 (held-out part combinations)
use types 1-10 on training objects, test4 types 11-16 on them; test2 and test5 use types 1-10 on their own objects.
"""

from __future__ import annotations

import json
import math
import os
import zlib
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from partinstruct_mjx.atomic import atomic_write
from partinstruct_mjx.assets.partnet import category_slug
from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.sim.scene import OBJECT_X_RANGE, OBJECT_Y_RANGE
from partinstruct_mjx.tasks import slot_rules
from partinstruct_mjx.tasks.instructions import skill_instruction, task_instruction
from partinstruct_mjx.tasks.skills import SkillStep
from partinstruct_mjx.tasks.task_types import task_type
from partinstruct_mjx.tasks.vocabulary import (DIRECTIONS, HORIZONTAL, OPPOSITE, SPATIAL_PARTS, UNIT_DISTANCE,
                                                direction_vector)

SPLITS = ("train", "test1", "test2", "test3", "test4", "test5")
SEEN_TYPES = tuple(range(1, 11))
UNSEEN_TYPES = tuple(range(11, 17))
SPLIT_TYPES = {split: UNSEEN_TYPES if split == "test4" else SEEN_TYPES for split in SPLITS}

"""The original's workspace for object positions (spec 1.4)."""

MAX_ATTEMPTS = 200
"""Object and pose draws per episode before giving up (each draw that admits no valid task is redrawn)."""

SPLIT_ID_STRIDE = 1_000_000
"""ep_id = split index * stride + index within the split, so adding a split keeps the other ids."""

_REQUIRED = ("obj_id", "ep_id", "chain_params", "task_instruction", "obj_pose", "obj_scale")


@dataclass(frozen=True)
class Episode:
    """One task instance: an object at a pose, a task type with its filled skill chain, and the instructions."""

    obj_class: str
    obj_id: str
    ep_id: int
    task_type: int
    split: str
    chain: tuple[SkillStep, ...]
    task_instruction: str
    skill_instructions: tuple[str, ...]
    obj_pose: tuple[float, ...]
    """[qx, qy, qz, qw, x, y, z], quaternion first like the original; z is ignored (the object is dropped)."""
    obj_scale: float
    seed: int | None = None
    """The per-episode seed everything was drawn from (None for the original's episodes)."""

    def slots(self) -> tuple[dict[str, str], dict[str, str]]:
        """The chain's slot values ({'P1': part, ...}, {'D1': word, ...}); TaskError if it does not fit the type."""
        return task_type(self.task_type).slots(self.chain)


def write_metadata(episodes, path: str | os.PathLike) -> None:
    """Write the nested metadata JSON atomically (temp file + rename); same episodes give the same bytes."""
    tree: dict = {}
    for ep in sorted(episodes, key=lambda e: (e.obj_class, _split_rank(e.split), e.task_type, e.ep_id)):
        tree.setdefault(ep.obj_class, {}).setdefault(ep.split, {}).setdefault(str(ep.task_type), []).append(
            _record(ep))
    with atomic_write(path) as file:
        json.dump(tree, file, indent=1)
        file.write("\n")


def _split_rank(split: str) -> tuple[int, str]:
    return (SPLITS.index(split), "") if split in SPLITS else (len(SPLITS), split)


def _record(ep: Episode) -> dict:
    record = {"obj_id": ep.obj_id, "ep_id": ep.ep_id, "chain_params": [s.to_metadata() for s in ep.chain],
              "task_instruction": ep.task_instruction, "skill_instructions": list(ep.skill_instructions),
              "obj_pose": list(ep.obj_pose), "obj_scale": ep.obj_scale}
    if ep.seed is not None:
        record["seed"] = ep.seed
    return record


def read_metadata(path: str | os.PathLike) -> list[Episode]:
    """Episodes of a metadata file (ours or the original's), sorted by ep_id; TaskError names file, episode, value.

    Missing skill instructions are filled from the skill templates, as the original does.
    """
    path = Path(path)
    try:
        tree = json.loads(path.read_text())
    except OSError as err:
        raise TaskError(f"{path}: cannot read episode metadata ({err.strerror})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise TaskError(f"{path}: not a JSON file ({err})") from None
    episodes = []
    for obj_class, by_split in _mapping(tree, f"{path}: top level").items():
        for split, by_type in _mapping(by_split, f"{path}: {obj_class}").items():
            for type_key, records in _mapping(by_type, f"{path}: {obj_class}/{split}").items():
                episodes += _episode_list(records, obj_class, split, type_key, f"{path}: {obj_class}/{split}")
    repeated = sorted(i for i, n in Counter(e.ep_id for e in episodes).items() if n > 1)
    if repeated:
        raise TaskError(f"{path}: ep_id {repeated[0]} is used by more than one episode")
    return sorted(episodes, key=lambda e: e.ep_id)


def _episode_list(records, obj_class: str, split: str, type_key: str, where: str) -> list[Episode]:
    try:
        type_id = task_type(type_key).id
    except TaskError as err:
        raise TaskError(f"{where}: {err}") from None
    if not isinstance(records, list):
        raise TaskError(f"{where}/{type_key}: expected a list of episodes")
    episodes = []
    for index, record in enumerate(records):
        try:
            episodes.append(_episode(record, obj_class, split, type_id))
        except TaskError as err:
            ep_id = record.get("ep_id") if isinstance(record, dict) else None
            named = f" (ep_id {ep_id})" if ep_id is not None else ""
            raise TaskError(f"{where}/{type_key}[{index}]{named}: {err}") from None
    return episodes


def _mapping(value, where: str) -> dict:
    if not isinstance(value, dict):
        raise TaskError(f"{where}: expected a JSON object, got {type(value).__name__}")
    return value


def _episode(record, obj_class: str, split: str, type_id: int) -> Episode:
    record = _mapping(record, "episode")
    missing = [field for field in _REQUIRED if field not in record]
    if missing:
        raise TaskError(f"missing field {', '.join(missing)}")
    ep_id = record["ep_id"]
    if not isinstance(ep_id, int) or isinstance(ep_id, bool):
        raise TaskError(f"ep_id must be an integer, got {ep_id!r}")
    chain = _chain(record["chain_params"])
    texts = record.get("skill_instructions") or [skill_instruction(step, obj_class) for step in chain]
    if not isinstance(texts, list) or len(texts) != len(chain) or not all(isinstance(t, str) for t in texts):
        raise TaskError(f"skill_instructions must be {len(chain)} strings (one per chain entry), got {texts!r}")
    if not isinstance(record["task_instruction"], str):
        raise TaskError(f"task_instruction must be a string, got {record['task_instruction']!r}")
    scale, seed = record["obj_scale"], record.get("seed")
    if not _is_number(scale) or scale <= 0:
        raise TaskError(f"obj_scale must be a positive number, got {scale!r}")
    if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool)):
        raise TaskError(f"seed must be an integer, got {seed!r}")
    return Episode(obj_class, str(record["obj_id"]), ep_id, type_id, split, chain, record["task_instruction"],
                   tuple(texts), _pose(record["obj_pose"]), float(scale), seed)


def _chain(params) -> tuple[SkillStep, ...]:
    if not isinstance(params, list) or not params:
        raise TaskError(f"chain_params must be a non-empty list, got {params!r}")
    steps = []
    for index, entry in enumerate(params):
        try:
            if not isinstance(entry, dict) or not isinstance(entry.get("params", {}), dict):
                raise TaskError(f"expected {{'skill_name': ..., 'params': {{...}}}}, got {entry!r}")
            steps.append(SkillStep.from_metadata(entry))
        except TaskError as err:
            raise TaskError(f"chain_params[{index}]: {err}") from None
    return tuple(steps)


def _pose(pose) -> tuple[float, ...]:
    if (not isinstance(pose, list) or len(pose) != 7 or not all(_is_number(v) and math.isfinite(v) for v in pose)
            or abs(math.hypot(*pose[:4]) - 1.0) > 1e-3):
        raise TaskError(f"malformed obj_pose {pose!r}: expected [qx, qy, qz, qw, x, y, z] with a unit quaternion")
    return tuple(float(v) for v in pose)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


# --- validation against the object library ------------------------------------------------------------------------

def validate_episode(episode: Episode, catalog_entry: dict) -> None:
    """Raise TaskError unless the episode's object is this catalog entry, its chain fits its task type and every
    part is one of the object's semantic parts, a spatial part or '' (the whole object)."""
    name = f"episode {episode.ep_id} ({episode.obj_class}/{episode.obj_id}, type {episode.task_type})"
    if (category_slug(episode.obj_class), episode.obj_id) != (catalog_entry["category"], catalog_entry["id"]):
        raise TaskError(f"{name}: catalog entry is {catalog_entry['category']}/{catalog_entry['id']}")
    known = set(catalog_entry["parts"]) | set(SPATIAL_PARTS) | {""}
    for step in episode.chain:
        if step.part is not None and step.part not in known:
            raise TaskError(f"{name}: unknown part '{step.part}' in {step.name}; {episode.obj_id} has "
                            f"{', '.join(catalog_entry['parts'])}, the spatial parts {', '.join(SPATIAL_PARTS)} "
                            f"and '' (the whole object)")
    try:
        episode.slots()
    except TaskError as err:
        raise TaskError(f"{name}: {err}") from None


def validate_episodes(episodes, catalog: list[dict]) -> None:
    """validate_episode for every episode, finding its object by category and id; TaskError if one is missing."""
    entries = {(e["category"], e["id"]): e for e in catalog}
    for episode in episodes:
        key = (category_slug(episode.obj_class), episode.obj_id)
        if key not in entries:
            raise TaskError(f"episode {episode.ep_id}: object {key[0]}/{key[1]} is not in the catalog")
        validate_episode(episode, entries[key])


# --- generation ---------------------------------------------------------------------------------------------------

def generate_episodes(catalog: list[dict], assets_root: str | os.PathLike, seed: int, per_type: int,
                      splits=SPLITS, cells: Callable[[str, int], bool] | None = None) -> list[Episode]:
    """`per_type` episodes per (split, category, task type), sorted by ep_id; with `cells`, only those of the
    (category, type) cells it admits, with the ep_ids and draws they have when every cell is drawn.

    Deterministic: episode i of (split, category, type) is drawn from a generator seeded with (seed, split,
    category, type, i), so adding a split or a category leaves the other draws unchanged; ep_ids count within
    their split from split index x SPLIT_ID_STRIDE, so adding a split leaves the other ids unchanged too.
    Test 3 has no episode where no held-out part combination can be done on the category's objects.
    """
    unknown = [s for s in splits if s not in SPLITS]
    if unknown:
        raise TaskError(f"unknown split '{unknown[0]}'; expected some of {', '.join(SPLITS)}")
    if seed < 0 or per_type < 1:
        raise TaskError(f"seed must be >= 0 and per_type >= 1, got seed {seed} and per_type {per_type}")
    vocabulary: dict[str, set[str]] = {}
    for entry in catalog:
        if "train" in entry["splits"]:
            vocabulary.setdefault(entry["category"], set()).update(entry["parts"])
    episodes = []
    for split in sorted(set(splits), key=SPLITS.index):
        members: dict[str, list[dict]] = {}
        for entry in sorted(catalog, key=lambda e: e["id"]):
            if split in entry["splits"]:
                members.setdefault(entry["category"], []).append(entry)
        index = 0
        for category, objects in sorted(members.items()):
            for type_id in SPLIT_TYPES[split]:
                held_out = slot_rules.held_out_combinations(category, type_id, vocabulary.get(category, ()))
                for i in range(per_type):
                    if cells is not None and not cells(category, type_id):
                        index += 1
                        continue
                    episode_seed = int(np.random.SeedSequence(
                        [seed, zlib.crc32(split.encode()), zlib.crc32(category.encode()), type_id, i]
                    ).generate_state(1)[0])
                    try:
                        episodes.append(_draw(objects, Path(assets_root), split, type_id, held_out, episode_seed,
                                              SPLITS.index(split) * SPLIT_ID_STRIDE + index))
                    except TaskError:
                        # Test 3's held-out part combinations are fixed by name; where none of them can be done on
                        # the category's objects (a bucket's wall under its bail cannot be grasped) the cell stays
                        # empty. Every other split has some valid task for every category and type.
                        if split != "test3":
                            raise
                    index += 1
    return episodes


def _draw(objects: list[dict], assets_root: Path, split: str, type_id: int, held_out: frozenset,
          episode_seed: int, ep_id: int) -> Episode:
    """One episode: redraw object and pose until the slot rules (and the split's held-out rule) admit a task, then
    draw which named parts are spatial, the parts, and the directions."""
    rng = np.random.default_rng(episode_seed)
    category = objects[0]["category"]
    for _ in range(MAX_ATTEMPTS):
        entry = objects[rng.integers(len(objects))]
        x, y, yaw = rng.uniform(*OBJECT_X_RANGE), rng.uniform(*OBJECT_Y_RANGE), rng.uniform(-math.pi, math.pi)
        object_dir = str(assets_root / entry["path"])
        views = slot_rules.part_views(slot_rules.load_object_geometry(object_dir), yaw)
        options = [(parts, dirs) for parts, dirs in slot_rules.feasible_assignments(type_id, category, views, (x, y))
                   if _split_admits(split, slot_rules.combination(type_id, parts) in held_out)]
        drawn = _draw_graspable(options, type_id, rng, lambda part: slot_rules.graspable(object_dir, yaw, part))
        if drawn is None:
            continue
        parts, choices = drawn
        directions = {slot: words[rng.integers(len(words))] for slot, words in choices.items()}
        chain = tuple(task_type(type_id).build_chain(parts, directions))
        if chain_reachable(object_dir, yaw, (x, y), chain):
            obj_class = category.replace("_", " ")
            return Episode(obj_class, entry["id"], ep_id, type_id, split, chain,
                           task_instruction(type_id, obj_class, parts, directions, episode_seed),
                           tuple(skill_instruction(step, obj_class) for step in chain),
                           (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2), x, y, 0.0),
                           float(entry["scale"]), episode_seed)
    raise TaskError(f"no valid {split} episode of type {type_id} for {category} after {MAX_ATTEMPTS} object and "
                    f"pose draws (seed {episode_seed}); its parts do not fit the slot rules or the arm's reach")


def chain_reachable(object_dir: str, yaw: float, position: tuple[float, float], chain) -> bool:
    """The arm reaches a grasp on each part the chain grasps and a touch pose on each part it touches, where the
    object is by then: moved by the chain's horizontal carries and pushes before (slot_rules.grasp_reachable,
    slot_rules.touch_reachable); and a grasp followed by a turn in the air has a grasp that fits the turn
    (slot_rules.air_turn_fits)."""
    x, y = position
    for index, (step, following) in enumerate(zip(chain, chain[1:] + (None,))):
        if step.name == "grasp_obj" and not (slot_rules.grasp_reachable(object_dir, yaw, step.part, (x, y))
                                             and slot_rules.air_turn_fits(object_dir, yaw, (x, y), chain, index)):
            return False
        if step.name == "touch_obj":
            pushed = following is not None and following.name == "move_gripper" and following.touching
            push_side = direction_vector(OPPOSITE[following.direction]) if pushed else np.zeros(3)
            if not slot_rules.touch_reachable(object_dir, yaw, step.part, (x, y), push_side):
                return False
        if step.name == "move_gripper" and step.direction in HORIZONTAL:
            x, y = x + UNIT_DISTANCE * DIRECTIONS[step.direction][0], y + UNIT_DISTANCE * DIRECTIONS[step.direction][1]
    return True


def _draw_graspable(options: list, type_id: int, rng: np.random.Generator, graspable) -> tuple | None:
    """Draw an assignment (first which named parts are spatial, then the assignment) whose grasped parts the gripper
    can close on; an assignment with a part `graspable` rejects is dropped with every other one grasping it. The
    grasp check is the costly rule, so it runs only on drawn parts (once each)."""
    grasped = [slot for slot, role in slot_rules.part_roles(type_id).items() if role == "grasp"]
    verdicts: dict[str, bool] = {}
    while options:
        kinds = sorted({_part_kinds(type_id, parts) for parts, _ in options})
        kind = kinds[rng.integers(len(kinds))]
        mine = [option for option in options if _part_kinds(type_id, option[0]) == kind]
        parts, choices = mine[rng.integers(len(mine))]
        for slot in grasped:
            if parts[slot] not in verdicts:
                verdicts[parts[slot]] = graspable(parts[slot])
        if all(verdicts[parts[slot]] for slot in grasped):
            return parts, choices
        options = [option for option in options if all(verdicts.get(option[0][slot], True) for slot in grasped)]
    return None


def _part_kinds(type_id: int, parts: dict[str, str]) -> tuple[bool, ...]:
    """Which named parts are spatial: drawn uniformly first, so semantic parts are as common as spatial ones."""
    return tuple(part in SPATIAL_PARTS for part in slot_rules.combination(type_id, parts))


def _split_admits(split: str, held_out: bool) -> bool:
    """Test 3 uses only held-out part combinations; train and test1 never do; the other splits use any."""
    if split == "test3":
        return held_out
    return not held_out or split not in ("train", "test1")


def summary(episodes) -> str:
    """Episode counts per split x task type, with the categories and objects each split uses."""
    episodes = list(episodes)
    splits = sorted({e.split for e in episodes}, key=_split_rank)
    types = sorted({e.task_type for e in episodes})
    counts = Counter((e.split, e.task_type) for e in episodes)
    header = ["split", "classes", "objects", *map(str, types), "total"]
    rows = [header]
    for split in splits:
        mine = [e for e in episodes if e.split == split]
        rows.append([split, str(len({e.obj_class for e in mine})), str(len({(e.obj_class, e.obj_id) for e in mine})),
                     *(str(counts[split, t]) for t in types), str(len(mine))])
    rows.append(["all", str(len({e.obj_class for e in episodes})),
                 str(len({(e.obj_class, e.obj_id) for e in episodes})),
                 *(str(sum(counts[s, t] for s in splits)) for t in types), str(len(episodes))])
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    return "\n".join("  ".join(cell.rjust(w) if i else cell.ljust(w) for i, (cell, w) in enumerate(zip(row, widths)))
                     for row in rows)
