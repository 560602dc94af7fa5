"""Episode generation, the metadata file (ours and the original's), instructions, split rules and the CLI."""

import argparse
import dataclasses
import json
import math
import string
from collections import Counter

import numpy as np
import pytest

from partinstruct_mjx.assets.catalog import load_catalog
from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.paths import assets_root
from partinstruct_mjx.tasks import slot_rules
from partinstruct_mjx.tasks.episodes import (SPLITS, generate_episodes, chain_reachable, read_metadata, summary,
                                             validate_episode, validate_episodes, write_metadata)
from partinstruct_mjx.tasks.episodes_cli import add_episodes_parser
from partinstruct_mjx.tasks.instructions import (TASK_TEMPLATES, instruction_slots, part_phrase, skill_instruction,
                                                 task_instruction)
from partinstruct_mjx.tasks.skills import SkillStep
from partinstruct_mjx.tasks.task_types import TASK_TYPES
from partinstruct_mjx.tasks.vocabulary import DIRECTIONS, HORIZONTAL, OPPOSITE, UNIT_DISTANCE


@pytest.fixture(scope="module")
def catalog():
    return load_catalog(assets_root())


@pytest.fixture(scope="module")
def episodes(catalog):
    return generate_episodes(catalog, assets_root(), seed=0, per_type=1)


def _entry(catalog, episode):
    return next(e for e in catalog if e["id"] == episode.obj_id)


def _yaw(episode):
    qx, qy, qz, qw = episode.obj_pose[:4]
    return 2 * math.atan2(qz, qw)


# --- determinism and the file -------------------------------------------------------------------------------------

def test_same_seed_gives_the_same_episodes_and_bytes_and_splits_are_independent(episodes, catalog, tmp_path):
    again = generate_episodes(catalog, assets_root(), seed=0, per_type=1, splits=("test5", "test2"))
    subset = [e for e in episodes if e.split in ("test2", "test5")]
    assert again == subset
    write_metadata(again, tmp_path / "a.json")
    write_metadata(subset, tmp_path / "b.json")
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()


def test_another_seed_gives_other_episodes(episodes, catalog):
    other = generate_episodes(catalog, assets_root(), seed=1, per_type=1, splits=("test5",))
    mine = [e for e in episodes if e.split == "test5"]
    assert len(other) == len(mine)
    assert [e.obj_pose for e in other] != [e.obj_pose for e in mine]
    assert [e.chain for e in other] != [e.chain for e in mine]


def test_write_then_read_gives_the_same_episodes(episodes, tmp_path):
    path = tmp_path / "episodes.json"
    write_metadata(episodes, path)
    assert read_metadata(path) == episodes
    assert not list(tmp_path.glob("*.tmp"))
    tree = json.loads(path.read_text())
    record = tree["bottle"]["train"]["1"][0]
    assert list(record) == ["obj_id", "ep_id", "chain_params", "task_instruction", "skill_instructions", "obj_pose",
                            "obj_scale", "seed"]


ORIGINAL = {"mug": {"test1": {
    "8": [{"obj_id": "8611", "ep_id": 1215,
           "chain_params": [{"skill_name": "grasp_obj", "params": {"part_grasp": "handle"}},
                            {"skill_name": "move_gripper", "params": {"dir_move": "top", "grasping": True,
                                                                      "touching": False, "put_down": False}},
                            {"skill_name": "rotate_obj", "params": {"part_rotate": "left", "dir_rotate": "front"}},
                            {"skill_name": "release_obj", "params": {}}],
           "task_instruction": "Lift the mug and show its left side to the front",
           "skill_instructions": ["Grasp the mug at its handle", "Move upwards",
                                  "Reorient the left of the mug to face front", "Release"],
           "obj_pose": [0.0, 0.0, -0.7071068, 0.7071068, 0.0387, -0.0315, 0.2], "obj_scale": 0.1}],
    "3": [{"obj_id": "8555", "ep_id": 7,
           "chain_params": [{"skill_name": "grasp_obj", "params": {"part_grasp": "body"}},
                            {"skill_name": "move_gripper", "params": {"dir_move": "left", "grasping": True,
                                                                      "touching": False, "put_down": False}}],
           "task_instruction": "Hold the body of the mug and move it to the left",
           "obj_pose": [0, 0, 0, 1, 0.061, -0.038, 0.2], "obj_scale": 0.1}]}}}
MUG_8555 = {"id": "8555", "category": "mug", "parts": ["handle", "body", "containing things"]}


def test_reads_the_original_format(tmp_path):
    path = tmp_path / "episodes_meta_test.json"
    path.write_text(json.dumps(ORIGINAL))
    first, second = read_metadata(path)
    assert (first.ep_id, first.task_type, first.obj_id, first.split) == (7, 3, "8555", "test1")
    assert first.skill_instructions == ("Grasp the mug at its body", "Move to the left")  # filled from templates
    assert first.obj_pose == (0.0, 0.0, 0.0, 1.0, 0.061, -0.038, 0.2) and first.seed is None
    assert second.chain[2] == SkillStep("rotate_obj", "left", "front")
    assert second.obj_pose[:4] == (0.0, 0.0, -0.7071068, 0.7071068) and second.obj_scale == 0.1
    validate_episode(first, MUG_8555)
    with pytest.raises(TaskError, match=r"episode 1215 .*does not fit task type 8"):
        validate_episode(second, {**MUG_8555, "id": "8611"})


def _broken(tmp_path, change) -> str:
    tree = json.loads(json.dumps(ORIGINAL))
    change(tree["mug"]["test1"])
    path = tmp_path / "broken.json"
    path.write_text(json.dumps(tree))
    with pytest.raises(TaskError) as err:
        read_metadata(path)
    assert "broken.json" in str(err.value)
    return str(err.value)


def test_bad_files_raise_errors_naming_file_episode_and_value(tmp_path):
    def direction(t):
        t["8"][0]["chain_params"][2]["params"]["dir_rotate"] = "sideways"

    def skill(t):
        t["3"][0]["chain_params"][0]["skill_name"] = "throw_obj"

    def type_17(t):
        t["17"] = t.pop("3")

    def pose(t):
        t["3"][0]["obj_pose"] = [0, 0, 0, 1, 0.1, 0.2]

    def missing(t):
        del t["3"][0]["chain_params"]

    message = _broken(tmp_path, direction)
    assert "ep_id 1215" in message and "sideways" in message and "chain_params[2]" in message
    assert "throw_obj" in _broken(tmp_path, skill)
    assert "'17'" in _broken(tmp_path, type_17)
    assert "ep_id 7" in _broken(tmp_path, pose) and "obj_pose" in _broken(tmp_path, pose)
    assert "missing field chain_params" in _broken(tmp_path, missing)


def test_unknown_part_is_named(tmp_path):
    path = tmp_path / "original.json"
    path.write_text(json.dumps(ORIGINAL))
    episode = read_metadata(path)[0]
    bad = dataclasses.replace(episode, chain=(SkillStep("grasp_obj", "spout"), episode.chain[1]))
    with pytest.raises(TaskError, match=r"episode 7 .*unknown part 'spout'"):
        validate_episode(bad, MUG_8555)
    with pytest.raises(TaskError, match="not in the catalog"):
        validate_episodes([episode], [])


# --- generated episodes -------------------------------------------------------------------------------------------

def test_generated_episodes_are_valid_and_their_instructions_name_their_slots(episodes, catalog):
    validate_episodes(episodes, catalog)
    assert len({e.ep_id for e in episodes}) == len(episodes)
    for ep in episodes:
        parts, directions = ep.slots()
        assert list(ep.chain) == TASK_TYPES[ep.task_type].build_chain(parts, directions)
        assert ep.obj_class in ep.task_instruction
        for slot in instruction_slots(ep.task_type):
            if slot in parts:
                assert part_phrase(parts[slot]) in ep.task_instruction, (ep.task_instruction, slot)
        assert ep.skill_instructions == tuple(skill_instruction(s, ep.obj_class) for s in ep.chain)
        assert ep.obj_scale == _entry(catalog, ep)["scale"] and ep.obj_pose[:2] == (0.0, 0.0)
        assert -0.05 <= ep.obj_pose[4] <= 0.08 and -0.085 <= ep.obj_pose[5] <= 0.2


def test_split_rules(episodes, catalog):
    membership = {e["id"]: e["splits"] for e in catalog}
    counts = Counter((e.split, e.obj_class, e.task_type) for e in episodes)
    assert set(counts.values()) == {1}
    for ep in episodes:
        assert ep.task_type in (range(11, 17) if ep.split == "test4" else range(1, 11))
        assert ep.split in membership[ep.obj_id]
    train_objects = {e["id"] for e in catalog if "train" in e["splits"]}
    assert not {e.obj_id for e in episodes if e.split in ("test2", "test5")} & train_objects
    held_out_categories = {e["category"].replace("_", " ") for e in catalog if "test5" in e["splits"]}
    assert {e.obj_class for e in episodes if e.split == "test5"} == held_out_categories
    assert not held_out_categories & {e.obj_class for e in episodes if e.split == "train"}


def test_test3_uses_only_part_combinations_never_seen_in_training(episodes, catalog):
    def key(ep):
        return ep.obj_class, ep.task_type, slot_rules.combination(ep.task_type, ep.slots()[0])

    seen = {key(e) for e in episodes if e.split in ("train", "test1")}
    vocabulary = {}
    for entry in catalog:
        if "train" in entry["splits"]:
            vocabulary.setdefault(entry["category"], set()).update(entry["parts"])
    for ep in (e for e in episodes if e.split == "test3"):
        assert key(ep) not in seen
        held_out = slot_rules.held_out_combinations(ep.obj_class.replace(" ", "_"), ep.task_type,
                                                    vocabulary[ep.obj_class.replace(" ", "_")])
        assert key(ep)[2] in held_out


def test_directions_fit_the_object_and_the_workspace(episodes, catalog):
    for ep in episodes:
        parts, directions = ep.slots()
        views = slot_rules.part_views(slot_rules.load_object_geometry(str(assets_root() / _entry(catalog, ep)["path"])),
                                      _yaw(ep))
        for slot, (role, part_slot) in slot_rules.direction_roles(ep.task_type).items():
            word = directions[slot]
            if role in ("move", "push"):
                x, y = (ep.obj_pose[4:6][i] + UNIT_DISTANCE * DIRECTIONS[word][i] for i in range(2))
                assert -0.2 <= x <= 0.25 and -0.25 <= y <= 0.35 and DIRECTIONS[word][2] == 0
            else:
                assert word != views[parts[part_slot]].facing
                assert role in ("rotate_air", "rotate_put_down") or DIRECTIONS[word][2] == 0
            if role == "rotate_put_down":
                assert ep.task_type in (11, 12, 16) and word in views[parts[part_slot]].put_down_facing
            if role == "opposite":
                assert ep.task_type == 15 and word == OPPOSITE[views[parts[part_slot]].facing]


def test_summary_counts_per_split_and_type(episodes):
    lines = summary(episodes).splitlines()
    assert lines[0].split()[:4] == ["split", "classes", "objects", "1"]
    train = lines[1].split()
    assert train[0] == "train" and train[-1] == str(sum(e.split == "train" for e in episodes))
    assert [line.split()[0] for line in lines[1:]] == [*SPLITS, "all"]


def test_bad_generation_arguments():
    with pytest.raises(TaskError, match="unknown split 'test9'"):
        generate_episodes([], assets_root(), 0, 1, splits=("test9",))
    with pytest.raises(TaskError, match="per_type"):
        generate_episodes([], assets_root(), 0, 0)


# --- instructions -------------------------------------------------------------------------------------------------

def test_skill_instructions_match_the_original_templates():
    assert skill_instruction(SkillStep("grasp_obj", "handle"), "kitchen pot") == "Grasp the kitchen pot at its handle"
    assert skill_instruction(SkillStep("touch_obj", "left"), "mug") == "Touch the mug at its left"
    assert skill_instruction(SkillStep("release_obj"), "mug") == "Release"
    faces = {w: skill_instruction(SkillStep("rotate_obj", "lid", w), "bottle") for w in DIRECTIONS}
    assert faces == {"left": "Reorient the lid of the bottle to face left",
                     "right": "Reorient the lid of the bottle to face right",
                     "front": "Reorient the lid of the bottle to face front",
                     "back": "Reorient the lid of the bottle to face back",
                     "top": "Reorient the lid of the bottle to face upwards",
                     "bottom": "Reorient the lid of the bottle to face downwards"}
    moves = [skill_instruction(SkillStep("move_gripper", direction=w), "mug") for w in DIRECTIONS]
    assert moves == ["Move to the left", "Move to the right", "Move forwards", "Move backwards", "Move upwards",
                     "Move downwards"]


def test_task_templates_have_distinct_variants_that_keep_every_slot():
    for type_id, variants in TASK_TEMPLATES.items():
        assert len(variants) >= 5 and len(set(variants)) == len(variants)
        for variant in variants:
            fields = {s.removesuffix("_face") for s in _fields(variant)}
            assert fields & {"obj", "obj_s"} and fields - {"obj", "obj_s"} == set(instruction_slots(type_id))
        goal_slots = {s for phase in TASK_TYPES[type_id].phases for g in phase
                      for s in (g.part, g.direction, *g.offset) if s and s[0] in "PD" and s[1:].isdigit()}
        assert set(instruction_slots(type_id)) == goal_slots - ({"D1"} if type_id == 15 else set())


def _fields(template):
    return {name for _, name, _, _ in string.Formatter().parse(template) if name}


def test_task_instruction_is_deterministic_and_reads_naturally():
    parts, directions = {"P1": "handle", "P2": "left"}, {"D1": "left", "D2": "top"}
    texts = {task_instruction(10, "mug", parts, directions, seed) for seed in range(12)}
    assert len(texts) == len(TASK_TEMPLATES[10])
    assert task_instruction(10, "mug", parts, directions, 3) == task_instruction(10, "mug", parts, directions, 3)
    assert task_instruction(10, "mug", parts, directions, 0) == (
        "Move the mug to the left in the air, then rotate the left part to point upwards")
    assert task_instruction(4, "scissors", {"P1": "blade"}, {"D1": "front"}, 2) == (
        "With the gripper against the scissors' blade, push the scissors forwards")
    with pytest.raises(TaskError, match="needs P2"):
        task_instruction(15, "mug", {"P1": "handle"}, {}, 0)


# --- command line -------------------------------------------------------------------------------------------------

def _run(argv):
    parser = argparse.ArgumentParser(prog="partinstruct")
    add_episodes_parser(parser.add_subparsers())
    args = parser.parse_args(["episodes", *argv])
    return args.func(args)


def test_cli_writes_and_checks(tmp_path, capsys):
    out = tmp_path / "meta.json"
    assert _run(["--out", str(out), "--splits", "test5", "--per-type", "1", "--seed", "3"]) == 0
    assert "wrote 30 episodes" in capsys.readouterr().out
    assert _run(["--check", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "30 episodes, all valid" in printed and "test5" in printed
    original = tmp_path / "original.json"
    original.write_text(json.dumps(ORIGINAL))
    with pytest.raises(TaskError, match="mug/8555 is not in the catalog"):
        _run(["--check", str(original)])


def test_slot_rules_judge_the_object_as_it_settles_on_the_table():
    # Built-in scissors rest on a ring and the blade tips: dropped unturned they tilt about 2 degrees, and the rules
    # see them resting on points spread over their whole length (not on one end, as the raw rest pose has it).
    folder = assets_root() / "objects" / "scissors" / "scissors_006"
    tilt = slot_rules.settled_tilt(folder / "object.xml")
    assert 0.5 < math.degrees(math.acos(min(1.0, (tilt.trace() - 1.0) / 2.0))) < 5.0
    assert abs(tilt[1, 0]) < 1e-6  # the heading is taken out: the episode's yaw says where the object points
    points = slot_rules.load_object_geometry(str(folder)).object_points

    def support_share(p):
        low = p[:2, p[2] < p[2].min() + 0.001]
        return (low.max(axis=1) - low.min(axis=1)) / (p[:2].max(axis=1) - p[:2].min(axis=1))

    assert support_share(tilt.T @ points).min() < 0.3
    assert support_share(points).min() > 0.7


def test_graspable_and_pushable_follow_the_gripper_and_the_physics():
    objects = assets_root() / "objects"
    assert slot_rules.graspable(str(objects / "bottle" / "bottle_002"), 0.0, "neck")
    # The open pads' tips come down to 3 mm above the table: they pinch a pair of blades raised on the scissors'
    # finger rings, but not a closed laptop's base, a slab lying on the table.
    assert slot_rules.graspable(str(objects / "scissors" / "scissors_006"), 0.0, "blade")
    assert not slot_rules.graspable(str(objects / "laptop" / "laptop_000"), 0.0, "base frame")
    # A pad lands first on the widest part of what it closes on: a stapler's body under its wider lid is out of
    # reach. A bucket's body has grasps (on its rim) only under some keys: its raised handle blocks the hand.
    assert not slot_rules.graspable(str(objects / "stapler" / "stapler_006"), 0.0, "body")
    assert not slot_rules.graspable(str(objects / "bucket" / "bucket_005"), 0.0, "base body")
    box = slot_rules.part_views(slot_rules.load_object_geometry(str(objects / "box" / "box_000")), 0.0)
    assert box["right"].pushable == {"left"} and box["left"].pushable == {"right"}
    # Pushing a standing bottle at its neck would tip it over.
    bottle = slot_rules.part_views(slot_rules.load_object_geometry(str(objects / "bottle" / "bottle_002")), 0.0)
    assert not bottle["neck"].pushable and bottle["body"].pushable == {"left", "right", "front", "back"}


def test_episodes_only_grasp_and_touch_where_the_arm_reaches():
    # A laptop turned 82 degrees at the far side of the object range (episode 387 of docs/oracle.md's first 880):
    # the oracle found no grasp on its front edge the arm reaches, only on the edge towards the robot.
    laptop = str(assets_root() / "objects" / "laptop" / "laptop_005")
    assert not slot_rules.grasp_reachable(laptop, 1.4375, "front", (-0.0075, 0.1276))
    assert slot_rules.grasp_reachable(laptop, 1.4375, "back", (-0.0075, 0.1276))
    # A stapler turned -94 degrees (episode 505 of the same draw): its base body, under the lid, has no touch pose the
    # oracle's search would use; the lid has.
    stapler = str(assets_root() / "objects" / "stapler" / "stapler_003")
    touch = [slot_rules.touch_reachable(stapler, -1.6345, part, (0.0759, 0.1199), np.zeros(3))
             for part in ("base body", "lid")]
    assert touch == [False, True]
    # A bottle's neck grasped after pushes away from the robot (12 cm each): reachable after two, not after three.
    bottle = str(assets_root() / "objects" / "bottle" / "bottle_002")
    push, grasp = SkillStep("move_gripper", None, "front", touching=True), SkillStep("grasp_obj", "neck")
    assert [chain_reachable(bottle, 0.0, (0.0, 0.05), (push,) * n + (grasp,)) for n in range(4)] == [
        True, True, True, False]



def test_a_push_needs_a_way_in_for_the_fingers():
    # laptop_003 turned 33 degrees (episode 4000226 of the seed-3 880 draw): its screen's back corner, low down, is
    # the push point for a push to the front, and the screen frame stands 1.3 cm out beside it there: the pads meet
    # the frame first. Its side can be pushed to the right.
    laptop = str(assets_root() / "objects" / "laptop" / "laptop_003")
    assert slot_rules.part_views(slot_rules.load_object_geometry(laptop), 0.5727)["screen"].pushable == {"right"}

def test_episodes_turn_an_object_in_the_air_only_where_a_grasp_fits_the_turn():
    # kitchen_pot_006 held by the knob on its lid, lifted, its base body to face the robot (episode 287 of the 880
    # draw, type 8): every grasp on the knob swings the pot 15 cm off the AT goal or leaves the arm out of reach, so
    # the task is not drawn. A bottle held by its cap, its bottom to face front (episode 35), has grasps that fit.
    lift, turn = SkillStep("move_gripper", None, "top", grasping=True), "rotate_obj"
    pot = str(assets_root() / "objects" / "kitchen_pot" / "kitchen_pot_006")
    pot_chain = (SkillStep("grasp_obj", "top"), lift, SkillStep(turn, "base body", "back"))
    assert not slot_rules.air_turn_fits(pot, 2.3607, (0.0737, -0.0252), pot_chain, 0)
    assert not chain_reachable(pot, 2.3607, (0.0737, -0.0252), pot_chain)
    bottle = str(assets_root() / "objects" / "bottle" / "bottle_000")
    bottle_chain = (SkillStep("grasp_obj", "top"), lift, SkillStep(turn, "bottom", "front"))
    assert slot_rules.air_turn_fits(bottle, 2.5782, (-0.0213, 0.1702), bottle_chain, 0)
    # Without a turn in the air (a turn on the table, or none) there is nothing to check.
    assert slot_rules.air_turn_fits(pot, 2.3607, (0.0737, -0.0252), pot_chain[:2], 0)


def test_turns_on_the_table_only_for_parts_a_yaw_can_make_face_the_goal():
    # A standing bottle's 'front' lies 2.9 cm out and 2.5 cm below its origin: a yaw turn keeps that 0.71 rad
    # elevation, so FACING (0.5 rad) could never hold; 5 mm below, it can.
    def view(z):
        return slot_rules.PartView(offset=np.array([-0.029, 0.0, z]), facing="front", exposed=frozenset(),
                                   pushable=frozenset(), put_down_facing=frozenset(DIRECTIONS))

    for role in ("rotate_table", "opposite"):
        assert slot_rules.direction_candidates(role, view(-0.025), []) == []
        assert slot_rules.direction_candidates(role, view(-0.005), [])
    assert slot_rules.direction_candidates("rotate_air", view(-0.025), [])


def test_turns_before_a_put_down_only_to_directions_the_object_can_lie_facing():
    # A knife's handle ('base body') faces up or down only with the knife standing on its end, its origin 9 cm
    # higher above its lowest point than lying down: the put-down's AT (8 cm) could never hold. Lying down it can
    # face any horizontal way; held in the air (type 8) any way at all.
    knife = slot_rules.load_object_geometry(str(assets_root() / "objects" / "knife" / "knife_004"))
    handle = slot_rules.part_views(knife, 0.3)["base body"]
    assert handle.put_down_facing == frozenset(HORIZONTAL)
    assert slot_rules.direction_roles(11)["D1"] == ("rotate_put_down", "P2")
    assert slot_rules.direction_roles(8)["D1"] == ("rotate_air", "P2")
    assert "bottom" in slot_rules.direction_candidates("rotate_air", handle, [])
    assert set(slot_rules.direction_candidates("rotate_put_down", handle, [])) <= set(HORIZONTAL)
    assert all({g.threshold for g in TASK_TYPES[t].phases[-1] if g.kind == "AT"} == {slot_rules.PUT_DOWN_AT_THRESHOLD}
               for t in (11, 12, 16))
    bottle = slot_rules.load_object_geometry(str(assets_root() / "objects" / "bottle" / "bottle_002"))
    assert all(view.put_down_facing == frozenset(DIRECTIONS) for view in slot_rules.part_views(bottle, 0.3).values())
