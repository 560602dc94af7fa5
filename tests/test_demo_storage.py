"""Demonstration storage: robomimic round trip, resume, crash recovery, finalize, summary and input checks."""

import dataclasses
import json

import h5py
import numpy as np
import pytest

from partinstruct_mjx.assets.catalog import load_catalog
from partinstruct_mjx.data.demos import Demo, DemoWriter, load_sidecar, read_demos
from partinstruct_mjx.errors import DataError
from partinstruct_mjx.paths import assets_root
from partinstruct_mjx.tasks.episodes import generate_episodes, read_metadata

ENV_ARGS = {"env_name": "PartInstruct", "type": 1, "env_kwargs": {"control_freq": 10}}


@pytest.fixture(scope="module")
def episodes():
    """One train episode per category and task type; ep_id -> Episode."""
    return {e.ep_id: e for e in generate_episodes(load_catalog(assets_root()), assets_root(), seed=0, per_type=1,
                                                   splits=("train",))}


def by_class(episodes, obj_class, count):
    return [e for e in episodes.values() if e.obj_class == obj_class][:count]


def make_demo(episode, steps=6, points=16):
    rng = np.random.default_rng(episode.ep_id)
    return Demo(episode=episode,
                actions=rng.normal(size=(steps, 7)).astype(np.float32),
                obs={"agentview_pcd": rng.normal(size=(steps, points, 3)).astype(np.float32),
                     "agentview_part_pcd": rng.normal(size=(steps, points, 4)).astype(np.float32),
                     "tcp_pose": rng.normal(size=(steps, 7)), "gripper_state": rng.normal(size=(steps, 1))},
                skill_index=np.arange(steps) * len(episode.chain) // steps,
                initial_state=rng.normal(size=30))


def files(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and p.name != ".lock")


def test_round_trip_robomimic_layout(tmp_path, episodes):
    mugs, bottle = by_class(episodes, "mug", 3), by_class(episodes, "bottle", 1)[0]
    demos = [make_demo(mugs[2], steps=4), make_demo(mugs[0], steps=7), make_demo(bottle)]
    writer = DemoWriter(tmp_path, ENV_ARGS)
    writer.add(demos, [(mugs[1], "grasp_obj")])
    writer.finalize()

    with h5py.File(tmp_path / "data" / "mug.hdf5", "r") as file:
        data = file["data"]
        assert sorted(data) == ["demo_0", "demo_1"]
        assert data.attrs["total"] == 11 and json.loads(data.attrs["env_args"]) == ENV_ARGS
        cloud = data["demo_0/obs/agentview_pcd"]
        assert cloud.chunks == (7, 16, 3) and cloud.compression == "lzf" and cloud.shuffle  # 7 steps: one chunk
        assert data["demo_0/skill_instructions"].dtype.kind == "O"
    read = list(read_demos(tmp_path / "data" / "mug.hdf5"))
    assert [name for name, _ in read] == ["demo_0", "demo_1"]
    for (_, arrays), demo in zip(read, sorted(demos[:2], key=lambda d: d.episode.ep_id)):
        episode = demo.episode
        attrs = arrays["attrs"]
        assert (attrs["num_samples"], attrs["ep_id"], attrs["seed"], attrs["task_type"]) == (
            demo.steps, episode.ep_id, episode.seed, episode.task_type)
        assert (attrs["split"], attrs["obj_id"], attrs["task_instruction"]) == (
            "train", episode.obj_id, episode.task_instruction)
        np.testing.assert_array_equal(arrays["actions"], demo.actions)
        assert arrays["actions"].dtype == np.float32 and arrays["skill_index"].dtype == np.int32
        np.testing.assert_array_equal(arrays["skill_index"], demo.skill_index)
        np.testing.assert_array_equal(arrays["initial_state"], demo.initial_state)
        assert [s.decode() for s in arrays["skill_instructions"]] == [
            episode.skill_instructions[i] for i in demo.skill_index]
        assert arrays["obs"].keys() == demo.obs.keys()
        for key, value in demo.obs.items():
            np.testing.assert_array_equal(arrays["obs"][key], value)
    assert [n for n, _ in read_demos(tmp_path / "data" / "bottle.hdf5")] == ["demo_0"]

    sidecar = load_sidecar(tmp_path, mugs[2].ep_id)
    assert sidecar["success"] and sidecar["failing_skill"] is None and sidecar["steps"] == 4
    assert sidecar["initial_state"] == demos[0].initial_state.tolist()
    assert sidecar["skill_boundaries"] == demos[0].skill_boundaries
    assert sidecar["chain_params"] == [s.to_metadata() for s in mugs[2].chain]
    assert (tmp_path / sidecar["shard"]).is_file() and sidecar["demo"] == f"ep_{mugs[2].ep_id}"
    failure = load_sidecar(tmp_path, mugs[1].ep_id)
    assert not failure["success"] and failure["failing_skill"] == "grasp_obj" and failure["shard"] is None
    assert read_metadata(tmp_path / "metadata.json") == sorted([mugs[0], mugs[2], bottle], key=lambda e: e.ep_id)


def test_resume_sees_finished_ids_and_rejects_them_again(tmp_path, episodes):
    mugs = by_class(episodes, "mug", 4)
    DemoWriter(tmp_path, ENV_ARGS).add([make_demo(mugs[2]), make_demo(mugs[3])], [(mugs[1], "timeout")])

    resumed = DemoWriter(tmp_path, ENV_ARGS)
    assert resumed.finished_ids() == {mugs[1].ep_id, mugs[2].ep_id, mugs[3].ep_id}
    before = files(tmp_path)
    for demos, failures in (([make_demo(mugs[0]), make_demo(mugs[2])], []), ([make_demo(mugs[0])], [(mugs[1], "x")])):
        with pytest.raises(DataError, match="already committed"):
            resumed.add(demos, failures)
    assert files(tmp_path) == before
    resumed.add([make_demo(mugs[0])], [])
    resumed.finalize()
    assert [a["attrs"]["ep_id"] for _, a in read_demos(tmp_path / "data" / "mug.hdf5")] == [
        mugs[0].ep_id, mugs[2].ep_id, mugs[3].ep_id]
    with pytest.raises(DataError, match="env_args"):
        DemoWriter(tmp_path, {**ENV_ARGS, "type": 2})


@pytest.mark.parametrize("sidecars_written", [0, 1])
def test_interrupted_batch_is_not_counted_nor_merged(tmp_path, episodes, sidecars_written):
    mugs = by_class(episodes, "mug", 4)
    writer = DemoWriter(tmp_path, ENV_ARGS)
    writer.add([make_demo(mugs[0])], [])
    ledger = (tmp_path / "progress.json").read_bytes()
    writer.add([make_demo(mugs[1]), make_demo(mugs[2])], [(mugs[3], "touch_obj")])
    # Crash before the ledger commit, after the shard and `sidecars_written` of the batch's sidecars.
    (tmp_path / "progress.json").write_bytes(ledger)
    for episode in [mugs[1], mugs[2], mugs[3]][sidecars_written:]:
        (tmp_path / "episodes" / f"{episode.ep_id}.json").unlink()
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / ".mug.abc.tmp.hdf5").write_bytes(b"partial")

    resumed = DemoWriter(tmp_path, ENV_ARGS)
    assert resumed.finished_ids() == {mugs[0].ep_id}
    assert files(tmp_path) == ["episodes/" f"{mugs[0].ep_id}.json", "progress.json",
                               f"shards/mug/{mugs[0].ep_id}-1.hdf5"]
    resumed.finalize()
    assert [a["attrs"]["ep_id"] for _, a in read_demos(tmp_path / "data" / "mug.hdf5")] == [mugs[0].ep_id]
    resumed.add([make_demo(mugs[2])], [(mugs[1], "grasp_obj")])
    assert resumed.finalize()["successes"] == 2


def test_finalize_twice_gives_identical_files(tmp_path, episodes):
    writer = DemoWriter(tmp_path, ENV_ARGS)
    writer.add([make_demo(e) for e in by_class(episodes, "mug", 3) + by_class(episodes, "knife", 2)], [])
    first = writer.finalize()
    outputs = ["data/mug.hdf5", "data/knife.hdf5", "metadata.json"]
    before = [(tmp_path / name).read_bytes() for name in outputs]
    second = DemoWriter(tmp_path, ENV_ARGS).finalize()
    assert [(tmp_path / name).read_bytes() for name in outputs] == before
    assert {k: v for k, v in first.items() if k != "provenance"} == {
        k: v for k, v in second.items() if k != "provenance"}
    assert json.loads((tmp_path / "summary.json").read_text()) == second


def test_summary_counts_failures_per_type_and_skill(tmp_path, episodes):
    pick = {t: [e for e in episodes.values() if e.task_type == t] for t in (1, 5)}
    writer = DemoWriter(tmp_path, ENV_ARGS)
    writer.add([make_demo(pick[1][0]), make_demo(pick[5][0])],
               [(pick[1][1], "timeout"), (pick[5][1], "grasp_obj"), (pick[5][2], "grasp_obj"),
                (pick[5][3], "rotate_obj")])
    summary = writer.finalize()
    assert (summary["episodes"], summary["successes"], summary["failures"]) == (6, 2, 4)
    assert summary["per_task_type"]["5"] == {"episodes": 4, "successes": 1, "failures": 3, "success_rate": 0.25,
                                             "failing_skills": {"grasp_obj": 2, "rotate_obj": 1}}
    assert summary["per_task_type"]["1"]["failing_skills"] == {"timeout": 1}
    assert summary["steps"] == 12 and sum(summary["demos_per_category"].values()) == 2
    assert {"date", "git_sha", "machine", "versions"} <= summary["provenance"].keys()


@pytest.mark.parametrize("change, words", [
    ({"actions": np.zeros((6, 6))}, "actions"),
    ({"obs": {"tcp_pose": np.zeros((5, 7))}}, "obs['tcp_pose']"),
    ({"skill_index": np.array([0, 0, 1, 0, 1, 1])}, "skill_index"),
    ({"initial_state": np.full(30, np.nan)}, "initial_state"),
])
def test_malformed_demo_names_episode_and_field(episodes, change, words):
    episode = episodes[3]
    fields = {f.name: getattr(make_demo(episode), f.name) for f in dataclasses.fields(Demo)}
    with pytest.raises(DataError, match=rf"episode 3: {words}".replace("[", r"\[").replace("]", r"\]")):
        Demo(**{**fields, **change})


def test_bad_batch_leaves_nothing_written(tmp_path, episodes):
    mugs = by_class(episodes, "mug", 3)
    writer = DemoWriter(tmp_path, ENV_ARGS)
    writer.add([make_demo(mugs[0])], [])
    before = files(tmp_path)
    alien = dataclasses.replace(mugs[2], obj_class="spaceship")
    fewer_points = make_demo(mugs[1], points=8)
    for demos, failures, message in (
            ([make_demo(mugs[1])], [(alien, "timeout")], f"episode {alien.ep_id}: unknown category 'spaceship'"),
            ([make_demo(mugs[1])], [(mugs[1], "timeout")], f"episode {mugs[1].ep_id} appears more than once"),
            ([make_demo(mugs[2]), fewer_points], [], f"episode {mugs[1].ep_id}: obs\\['agentview_part_pcd'\\]"),
            ([], [(mugs[1], "")], "failing skill")):
        with pytest.raises(DataError, match=message):
            writer.add(demos, failures)
    assert files(tmp_path) == before and writer.finished_ids() == {mugs[0].ep_id}


def test_batch_failing_midway_removes_what_it_wrote(tmp_path, episodes):
    mugs = by_class(episodes, "mug", 2)
    writer = DemoWriter(tmp_path, ENV_ARGS)
    blocker = tmp_path / "episodes" / f"{mugs[1].ep_id}.json"
    blocker.mkdir(parents=True)  # the second sidecar cannot be written
    with pytest.raises(OSError):
        writer.add([make_demo(mugs[0]), make_demo(mugs[1])], [])
    assert files(tmp_path) == ["progress.json"] and writer.finished_ids() == set()
    blocker.rmdir()
    writer.add([make_demo(mugs[0]), make_demo(mugs[1])], [])
    assert writer.finished_ids() == {mugs[0].ep_id, mugs[1].ep_id}
