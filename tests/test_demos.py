"""`partinstruct demos`: what a run writes, resume, reproducibility, cloud shapes, replay, episode choice, help."""

import json
import os
from collections import Counter

import numpy as np
import pytest

from partinstruct_mjx.assets.catalog import load_catalog
from partinstruct_mjx.cli import main
from partinstruct_mjx.data.demos import read_demos
from partinstruct_mjx.data import synthesis
from partinstruct_mjx.data.synthesis import remembered_selection, select_episodes
from partinstruct_mjx.paths import assets_root
from partinstruct_mjx.tasks.episodes import generate_episodes, write_metadata


@pytest.fixture(scope="module")
def metadata(tmp_path_factory):
    """Two grasp and two touch train episodes of one bottle (one object and batch size: one compile)."""
    root = assets_root()
    episodes = generate_episodes([e for e in load_catalog(root) if e["category"] == "bottle"], root, seed=0,
                                 per_type=12, splits=("train",))
    count = Counter((e.obj_id, e.task_type) for e in episodes)
    obj_id = max(sorted({e.obj_id for e in episodes}), key=lambda o: min(count[o, 1], count[o, 2]))
    chosen = [e for t in (1, 2) for e in [e for e in episodes if e.obj_id == obj_id and e.task_type == t][:2]]
    assert len(chosen) == 4
    path = tmp_path_factory.mktemp("episodes") / "bottle.json"
    write_metadata(chosen, path)
    return path


def demos(metadata, out, count, *extra):
    return main(["demos", "--metadata", str(metadata), "--episodes", str(count), "--batch-size", "2", "--out",
                 str(out), "--quiet", *extra])


@pytest.fixture(scope="module")
def run_dir(metadata, tmp_path_factory):
    out = tmp_path_factory.mktemp("demos") / "run"
    assert demos(metadata, out, 2) == 0
    return out


def test_run_writes_demos_sidecars_and_summary(run_dir):
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["episodes"] == 2 and summary["successes"] + summary["failures"] == 2
    assert sorted(summary["per_task_type"]) == ["1", "2"]
    sidecars = sorted(run_dir.glob("episodes/*.json"))
    assert len(sidecars) == 2
    records = [json.loads(p.read_text()) for p in sidecars]
    for record in records:
        assert record["success"] == (record["failing_skill"] is None)
        if not record["success"]:
            assert record["failing_skill"] in ("grasp_obj", "touch_obj", "step_limit", "no_task_success")
    assert (run_dir / "metadata.json").exists()
    assert (run_dir / "data" / "bottle.hdf5").exists() == (summary["successes"] > 0)
    env_args = json.loads((run_dir / "progress.json").read_text())["env_args"]
    assert env_args["env_kwargs"]["skill_mode"] is False and env_args["synthesis"]["seed"] == 0


def test_demos_hold_clouds_and_state_per_step(run_dir):
    if not (run_dir / "data" / "bottle.hdf5").exists():
        pytest.skip("the oracle succeeded on no episode, so there is no demo to inspect")
    for _, demo in read_demos(run_dir / "data" / "bottle.hdf5"):
        steps = demo["attrs"]["num_samples"]
        obs = demo["obs"]
        assert demo["actions"].shape == (steps, 7) and demo["skill_index"].shape == (steps,)
        assert obs["agentview_pcd"].shape == (steps, 1024, 3) and obs["agentview_pcd"].dtype == np.float32
        assert obs["agentview_part_pcd"].shape == (steps, 1024, 4)
        np.testing.assert_array_equal(obs["agentview_part_pcd"][..., :3], obs["agentview_pcd"])
        assert set(np.unique(obs["agentview_part_pcd"][..., 3])) <= {0.0, 1.0}
        assert obs["agentview_part_pcd"][..., 3].any(), "the grasped/touched part is never in view"
        assert (obs["agentview_pcd"][..., 2] > 0).all(), "points behind the camera"
        for key, size in (("tcp_pose", 7), ("joint_states", 7), ("gripper_state", 1), ("object_pose", 7)):
            assert obs[key].shape == (steps, size)


def test_rerun_resumes_and_more_episodes_adds_only_new_ones(metadata, run_dir, capsys):
    ledger = json.loads((run_dir / "progress.json").read_text())["episodes"]
    shards = sorted(p.name for p in run_dir.glob("shards/*/*"))
    capsys.readouterr()
    assert demos(metadata, run_dir, 2) == 0
    assert "0 episodes run now" in capsys.readouterr().out
    assert json.loads((run_dir / "progress.json").read_text())["episodes"] == ledger
    assert sorted(p.name for p in run_dir.glob("shards/*/*")) == shards

    assert demos(metadata, run_dir, 4) == 0
    assert "2 episodes run now" in capsys.readouterr().out
    now = json.loads((run_dir / "progress.json").read_text())["episodes"]
    assert len(now) == 4 and {k: now[k] for k in ledger} == ledger
    assert json.loads((run_dir / "summary.json").read_text())["episodes"] == 4


def test_ctrl_c_while_the_next_batch_runs_keeps_the_batch_being_written(metadata, tmp_path, monkeypatch, capsys):
    """Clouds and writing run beside the next batch's simulation: Ctrl-C there waits for the batch being written,
    and the same command resumes with only the rest."""
    import time

    from partinstruct_mjx.oracle import rollout

    real_run, real_commit = rollout.run_oracle, synthesis._ObjectWorker.commit

    def interrupted_after_two(*args, **kwargs):
        for count, episode in enumerate(real_run(*args, **kwargs), 1):
            yield episode
            if count == 2:
                raise KeyboardInterrupt

    def slow_commit(self, batch, writer):
        time.sleep(1.0)  # still writing when Ctrl-C comes
        return real_commit(self, batch, writer)

    monkeypatch.setattr(rollout, "run_oracle", interrupted_after_two)
    monkeypatch.setattr(synthesis._ObjectWorker, "commit", slow_commit)
    assert demos(metadata, tmp_path, 4) == 130
    first = json.loads((tmp_path / "progress.json").read_text())["episodes"]
    assert len(first) == 2 and len(list(tmp_path.glob("episodes/*.json"))) == 2
    monkeypatch.undo()
    capsys.readouterr()
    assert demos(metadata, tmp_path, 4) == 0
    assert "2 episodes run now" in capsys.readouterr().out
    now = json.loads((tmp_path / "progress.json").read_text())["episodes"]
    assert len(now) == 4 and {k: now[k] for k in first} == first


def test_same_arguments_give_the_same_demos(metadata, run_dir, tmp_path):
    assert demos(metadata, tmp_path, 2) == 0
    first = {json.loads(p.read_text())["ep_id"]: json.loads(p.read_text()) for p in tmp_path.glob("episodes/*")}
    again = {ep_id: json.loads((run_dir / "episodes" / f"{ep_id}.json").read_text()) for ep_id in first}
    for ep_id, record in first.items():
        assert (record["success"], record["steps"], record["failing_skill"]) == (
            again[ep_id]["success"], again[ep_id]["steps"], again[ep_id]["failing_skill"])
    if (tmp_path / "data" / "bottle.hdf5").exists():
        stored = {d["attrs"]["ep_id"]: d for _, d in read_demos(run_dir / "data" / "bottle.hdf5")}
        for _, a in read_demos(tmp_path / "data" / "bottle.hdf5"):
            b = stored[a["attrs"]["ep_id"]]
            np.testing.assert_array_equal(a["actions"], b["actions"])
            np.testing.assert_array_equal(a["obs"]["agentview_part_pcd"], b["obs"]["agentview_part_pcd"])


def test_demos_do_not_depend_on_the_workers(tmp_path):
    """Two objects simulated at once, in two threads, give the demos they give one after the other."""
    root = assets_root()
    episodes = generate_episodes([e for e in load_catalog(root) if e["category"] == "bottle"], root, seed=0,
                                 per_type=12, splits=("train",))
    touches = [e for e in episodes if e.task_type == 2]
    objects = sorted({e.obj_id for e in touches})[:2]
    chosen = [e for obj_id in objects for e in [e for e in touches if e.obj_id == obj_id][:2]]
    assert len(chosen) == 4
    runs = {}
    for workers in (1, 2):
        summary = synthesis.synthesize(chosen, tmp_path / str(workers), batch_size=2, progress=False, oracle_tries=1,
                                       workers=workers)
        assert summary["run"]["workers"] == workers
        runs[workers] = {p.name: json.loads(p.read_text()) for p in (tmp_path / str(workers)).glob("episodes/*")}
        if (tmp_path / str(workers) / "data" / "bottle.hdf5").exists():
            runs[workers]["actions"] = {d["attrs"]["ep_id"]: d["actions"].tolist()
                                        for _, d in read_demos(tmp_path / str(workers) / "data" / "bottle.hdf5")}
    assert runs[1].get("actions"), "no demo to compare"
    assert runs[1] == runs[2]


def test_other_settings_are_refused_for_an_existing_directory(metadata, run_dir, capsys):
    before = sorted(p.relative_to(run_dir) for p in run_dir.rglob("*"))
    assert demos(metadata, run_dir, 2, "--seed", "1") == 2
    assert "env_args" in capsys.readouterr().err
    assert demos(metadata, run_dir, 2, "--oracle-tries", "1") == 2  # the run used the default, 4
    assert "env_args" in capsys.readouterr().err
    assert demos(metadata, run_dir, 2, "--oracle-restarts", "0") == 2
    assert "env_args" in capsys.readouterr().err
    # refused before anything is written, also the episode selection a run without --metadata keeps
    assert main(["demos", "--episodes", "2", "--seed", "1", "--out", str(run_dir), "--quiet"]) == 2
    assert "env_args" in capsys.readouterr().err
    assert sorted(p.relative_to(run_dir) for p in run_dir.rglob("*")) == before


def test_replay_reproduces_stored_demos(run_dir, capsys):
    if not (run_dir / "data" / "bottle.hdf5").exists():
        pytest.skip("the oracle succeeded on no episode, so there is no demo to replay")
    capsys.readouterr()
    assert main(["demos", "--replay", str(run_dir / "data" / "bottle.hdf5"), "--batch-size", "2", "--limit", "2"]) == 0
    out = capsys.readouterr().out
    assert "demos reach task success within their stored length" in out and "NO" not in out


def test_zarr_export_stacks_every_step_in_dp3s_layout(run_dir, tmp_path, capsys):
    zarr = pytest.importorskip("zarr")
    stored = [demo for path in sorted((run_dir / "data").glob("*.hdf5")) for _, demo in read_demos(path)]
    if not stored:
        pytest.skip("the oracle succeeded on no episode, so there is no demo to export")
    out = tmp_path / "exports" / "run.zarr"
    assert main(["demos", "--export-zarr", str(run_dir), str(out), "--quiet"]) == 0
    assert f"{len(stored)} demos" in capsys.readouterr().out
    assert (out / ".zgroup").exists()  # zarr format 2, which DP3's zarr 2 reads
    root = zarr.open_group(out, mode="r")
    ends = np.cumsum([len(demo["actions"]) for demo in stored])
    np.testing.assert_array_equal(root["meta/episode_ends"][:], ends)
    np.testing.assert_array_equal(root["meta/ep_id"][:], [demo["attrs"]["ep_id"] for demo in stored])
    joined = {key: np.concatenate(values) for key, values in {
        "point_cloud": [d["obs"]["agentview_pcd"] for d in stored],
        "part_point_cloud": [d["obs"]["agentview_part_pcd"] for d in stored],
        "state": [np.concatenate([d["obs"][k] for k in ("tcp_pose", "joint_states", "gripper_state")], -1)
                  for d in stored],
        "object_pose": [d["obs"]["object_pose"] for d in stored],
        "action": [d["actions"] for d in stored], "skill_index": [d["skill_index"] for d in stored]}.items()}
    for key, expected in joined.items():
        np.testing.assert_array_equal(root["data"][key][:], expected, err_msg=key)
    first = root.attrs["episodes"][0]
    assert first["task_instruction"] == stored[0]["attrs"]["task_instruction"] and first["skill_instructions"]
    assert root.attrs["env_args"]["env_name"] == "PartInstructMJX"


def test_zarr_export_refuses_bad_input_and_leaves_nothing(run_dir, tmp_path, capsys):
    pytest.importorskip("zarr")
    import shutil

    import h5py

    taken = tmp_path / "taken.zarr"
    taken.mkdir()
    (taken / "mine").write_text("keep")
    assert main(["demos", "--export-zarr", str(run_dir), str(taken), "--quiet"]) == 2
    assert "already exists" in capsys.readouterr().err and (taken / "mine").read_text() == "keep"
    assert main(["demos", "--export-zarr", str(tmp_path), str(tmp_path / "a.zarr"), "--quiet"]) == 2
    assert "not a demos run directory" in capsys.readouterr().err
    assert main(["demos", "--export-zarr", str(run_dir), str(tmp_path / "b.zarr"), "--categories", "mug"]) == 2
    assert "no demos of mug" in capsys.readouterr().err
    files = sorted((run_dir / "data").glob("*.hdf5"))
    if not files:
        pytest.skip("the oracle succeeded on no episode, so there is no demo to break")
    broken = tmp_path / "broken"
    shutil.copytree(run_dir, broken)
    with h5py.File(broken / "data" / files[0].name, "a") as file:
        del file["data"][sorted(file["data"])[-1]]["obs"]["joint_states"]
    assert main(["demos", "--export-zarr", str(broken), str(tmp_path / "c.zarr"), "--quiet"]) == 2
    assert "obs/joint_states" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken", "taken.zarr"]


def test_episode_choice_spreads_over_types_and_categories():
    ten = select_episodes("train", 10)
    assert sorted(e.task_type for e in ten) == list(range(1, 11))
    assert len({e.obj_class for e in ten}) == 10
    sixteen = select_episodes("all-types", 16)
    assert sorted(e.task_type for e in sixteen) == list(range(1, 17))
    assert {e.split for e in sixteen if e.task_type > 10} == {"test4"}
    mugs = select_episodes("train", 3, types=[2], categories=["mug"])
    assert [(e.task_type, e.obj_class) for e in mugs] == [(2, "mug")] * 3
    # an ep_id names the same episode whatever the filters and the count
    seeds = {e.ep_id: e.seed for e in select_episodes("train", 400)}
    assert all(seeds[e.ep_id] == e.seed for e in ten + mugs)


def test_episodes_drawn_in_worker_processes_are_the_same():
    """A process pool draws each category's episodes in one of its processes: the same episodes, in the same order."""
    from partinstruct_mjx.workers import process_pool

    with process_pool(2) as pool:
        drawn = select_episodes("test1", 6, categories=["mug", "bottle"], pool=pool)
    assert drawn == select_episodes("test1", 6, categories=["mug", "bottle"])
    assert {e.obj_class for e in drawn} == {"mug", "bottle"}


def test_generated_selection_is_remembered_in_the_run_directory(tmp_path, monkeypatch):
    first = remembered_selection(tmp_path, "train", 5, seed=1, types=[2, 5], categories=["mug"])
    assert first == select_episodes("train", 5, seed=1, types=[2, 5], categories=["mug"])
    (stored,) = (tmp_path / "selections").iterdir()
    other = remembered_selection(tmp_path, "train", 3, seed=1, types=[2, 5], categories=["mug"])  # another file
    assert other == first[:3] and len(list((tmp_path / "selections").iterdir())) == 2

    def no_generation(*args, **kwargs):
        raise AssertionError("episodes were generated again")

    monkeypatch.setattr(synthesis, "generate_episodes", no_generation)
    assert remembered_selection(tmp_path, "train", 5, seed=1, types=[5, 2], categories=["mug"]) == first  # read back
    assert stored.exists()


def test_a_large_selection_is_drawn_in_one_process_per_core(tmp_path, monkeypatch):
    """From DRAW_IN_PROCESSES episodes on (here lowered to 4), a run directory's selection is drawn in a pool of one
    process per core; the episodes are those drawn in one process."""
    asked = []
    real_pool = synthesis.process_pool

    def spied_pool(processes):
        asked.append(processes)
        return real_pool(processes)

    monkeypatch.setattr(synthesis, "process_pool", spied_pool)
    monkeypatch.setattr(synthesis, "DRAW_IN_PROCESSES", 4)
    small = remembered_selection(tmp_path / "small", "train", 3, types=[2, 5], categories=["mug", "bottle"])
    large = remembered_selection(tmp_path / "large", "train", 4, types=[2, 5], categories=["mug", "bottle"])
    assert asked == [1, os.cpu_count() or 1]
    assert small == large[:3]
    assert large == select_episodes("train", 4, types=[2, 5], categories=["mug", "bottle"])


@pytest.mark.parametrize("args, message", [(["--split", "test9"], "unknown split"),
                                           (["--types", "12"], "not in split train"),
                                           (["--categories", "teapot"], "unknown category"),
                                           (["--oracle-tries", "0"], "--oracle-tries must be >= 1"),
                                           (["--oracle-restarts", "-1"], "--oracle-restarts must be >= 0"),
                                           (["--workers", "0"], "--workers must be >= 1")])
def test_bad_input_exits_2(tmp_path, capsys, args, message):
    assert main(["demos", "--out", str(tmp_path / "out"), *args]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_help_explains_outputs_and_resume(command_help):
    out = command_help("demos")
    assert "data/<category>.hdf5" in out and "resume" in out and "--replay" in out and "--export-zarr" in out


def test_generating_for_every_split_is_refused_by_name():
    from partinstruct_mjx.errors import TaskError

    with pytest.raises(TaskError, match="split None"):
        select_episodes(None, 10)


def test_failure_names_say_why_an_episode_is_not_a_demo():
    """The oracle's failed skill first; without one, a diverged simulation, then the step limit."""
    episode = select_episodes("train", 10, seed=0, categories=["mug"])[0]
    name = synthesis._failure_name
    assert name(episode, 0, 10, True) == episode.chain[0].name
    assert name(episode, -1, 10, True) == "physics_unstable"
    assert name(episode, -1, 250, False) == "step_limit"
    assert name(episode, -1, 10, False) == "no_task_success"
