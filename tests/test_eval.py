"""`partinstruct eval`: a real oracle evaluation, results.json schema, aggregation and standard errors, resume,
the policy and planner interfaces, errors."""

import json
import math
import os
import warnings
from dataclasses import replace

import imageio_ffmpeg
import jax
import numpy as np
import pytest

from partinstruct_mjx.cli import main
from partinstruct_mjx.data.synthesis import select_episodes
from partinstruct_mjx.env import EnvConfig, PartInstructEnv, hold_action
from partinstruct_mjx.eval import EvalConfig, EvalError, aggregate, evaluate
from partinstruct_mjx.eval.compare import mcnemar_p
from partinstruct_mjx.eval.metrics import mean_se, percent, results_markdown, success_table
from partinstruct_mjx.eval.planner import OraclePlanner
from partinstruct_mjx.eval.runner import _run_episodes, select_eval_episodes
from partinstruct_mjx.paths import assets_root
from partinstruct_mjx.tasks.episodes import read_metadata, write_metadata

MAX_STEPS = 60
RECORD_FIELDS = {"split": str, "category": str, "obj_id": str, "ep_id": int, "task_type": int, "success": bool,
                 "completion": float, "steps": int, "step_limit": int, "stopped_skill": (str, type(None)),
                 "skills": list, "skill_success": list, "target_parts": list, "task_instruction": str,
                 "video": (str, type(None)), "physics_unstable": bool}


@pytest.fixture(scope="module")
def metadata(tmp_path_factory):
    """A grasp and a touch test1 episode of one mug (one object and batch size: one compile)."""
    episodes = select_episodes("test1", 6, seed=0, categories=["mug"])
    chosen = [e for e in episodes if e.obj_id == episodes[0].obj_id][:2]
    assert [e.task_type for e in chosen] == [1, 2]
    path = tmp_path_factory.mktemp("episodes") / "mug.json"
    write_metadata(chosen, path)
    return path


def run(metadata, out, *extra):
    return main(["eval", "--policy", "oracle", "--metadata", str(metadata), "--splits", "test1", "--batch-size", "2",
                 "--max-steps", str(MAX_STEPS), "--out", str(out), "--quiet", *extra])


@pytest.fixture(scope="module")
def run_dir(metadata, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval") / "oracle"
    assert run(metadata, out, "--videos", "1") == 0
    return out


def test_oracle_evaluation_writes_results_and_a_video(run_dir):
    results = json.loads((run_dir / "results.json").read_text())
    assert results["complete"] is True and results["schema_version"] == 1
    assert {"config", "identity", "resolved", "run", "provenance", "summary", "episodes", "label"} <= set(results)
    assert results["provenance"]["git_sha"] and "jax" in results["provenance"]["versions"]
    assert results["config"]["policy"] == "oracle" and results["config"]["mode"] == "skill"
    assert results["resolved"]["step_limits"] == {"test1": MAX_STEPS}
    assert results["resolved"]["policy_class"] == "OraclePolicy"
    episodes = results["episodes"]
    assert len(episodes) == 2 and results["run"]["episodes_run"] == 2
    for record in episodes:
        for field, kind in RECORD_FIELDS.items():
            assert isinstance(record[field], kind), field
        assert record["split"] == "test1" and record["category"] == "mug"
        assert len(record["skill_success"]) == len(record["skills"]) == 1
        assert 1 <= record["steps"] <= MAX_STEPS and record["step_limit"] == MAX_STEPS
        # Skill mode: success is the whole chain completed, and completion the share of its skills.
        assert record["success"] == all(record["skill_success"]) == (record["stopped_skill"] is None)
        assert record["completion"] == pytest.approx(np.mean(record["skill_success"]))
        assert record["success"] or record["steps"] == MAX_STEPS
        assert record["target_parts"]
    first = episodes[0]
    assert first["video"] and episodes[1]["video"] is None
    frames = _frames(run_dir / first["video"])
    assert len(frames) == first["steps"] + 1, "one frame at reset and one per step until the episode ended"
    assert np.abs(frames[-1].astype(int) - frames[0]).mean() > 1.0, "the arm does not move in the video"
    report = (run_dir / "results.md").read_text()
    assert "| Policy | Test 1 (OS) | All |" in report and "## Per skill" in report


def _frames(path) -> list[np.ndarray]:
    with warnings.catch_warnings():  # ffmpeg is fork+exec'd, which JAX's fork warning does not concern
        warnings.filterwarnings("ignore", r"os\.fork\(\) was called", RuntimeWarning)
        reader = imageio_ffmpeg.read_frames(str(path))
        width, height = next(reader)["size"]
        return [np.frombuffer(frame, np.uint8).reshape(height, width, 3) for frame in reader]


def test_aggregates_recompute_from_the_stored_records(run_dir):
    results = json.loads((run_dir / "results.json").read_text())
    records = results["episodes"]
    assert aggregate(records, ["test1"]) == results["summary"]
    summary = results["summary"]
    successes = sum(r["success"] for r in records)
    assert summary["overall"]["successes"] == summary["per_split"]["test1"]["successes"] == successes
    p = successes / 2
    assert summary["overall"]["success_se"] == pytest.approx(math.sqrt(p * (1 - p) / 2))
    for record in records:
        skill = summary["per_skill"][record["skills"][0]]
        assert skill["reached"] >= 1 and skill["completed"] <= skill["reached"]
        assert summary["per_task_type"][str(record["task_type"])]["episodes"] == 1
        assert summary["per_part"][record["target_parts"][0]]["episodes"] >= 1


def test_standard_errors_match_the_papers_error_bars(run_dir):
    """DP3 on Test 1 in the paper: 23.18 +- 2.8 from 51 of 220 rollouts; here on records of the real run's schema."""
    template = json.loads((run_dir / "results.json").read_text())["episodes"][0]
    records = [template | {"ep_id": i, "success": i < 51, "completion": 1.0 if i < 51 else 0.5} for i in range(220)]
    records += [template | {"ep_id": 1000 + i, "split": "test5", "success": i < 2, "completion": 0.0}
                for i in range(30)]
    summary = aggregate(records, ["test1", "test5"])
    test1 = summary["per_split"]["test1"]
    assert test1["success_rate"] == pytest.approx(51 / 220)
    assert percent(test1["success_rate"], test1["success_se"]) == "23.18 ± 2.8"
    assert test1["completion_rate"] == pytest.approx((51 + 0.5 * 169) / 220)
    assert percent(summary["per_split"]["test5"]["success_rate"], summary["per_split"]["test5"]["success_se"]) \
        == "6.67 ± 4.6"
    # All pools the rollouts; the mean of the split rates is reported beside it.
    assert summary["overall"]["success_rate"] == pytest.approx(53 / 250)
    assert summary["mean_over_splits"]["success_rate"] == pytest.approx((51 / 220 + 2 / 30) / 2)
    assert mean_se([]) == (None, None) and mean_se([1, 1]) == (1.0, 0.0)
    table = success_table(summary, ["test1", "test5"], "DP3")
    assert "| DP3 | 23.18 ± 2.8 | 6.67 ± 4.6 | 21.20 ± 2.6 |" in table


def test_per_skill_counts_only_the_skills_an_episode_reached(run_dir):
    template = json.loads((run_dir / "results.json").read_text())["episodes"][0]
    chain = ["grasp_obj", "move_gripper", "release_obj"]
    records = [template | {"ep_id": 0, "skills": chain, "skill_success": [True, False, False], "success": False,
                           "target_parts": ["handle", ""], "physics_unstable": True},
               template | {"ep_id": 1, "skills": chain, "skill_success": [True, True, True], "success": True,
                           "target_parts": ["top"]}]
    summary = aggregate(records)
    assert summary["per_skill"]["grasp_obj"] == {"reached": 2, "completed": 2, "success_rate": 1.0}
    assert summary["per_skill"]["move_gripper"] == {"reached": 2, "completed": 1, "success_rate": 0.5}
    assert summary["per_skill"]["release_obj"] == {"reached": 1, "completed": 1, "success_rate": 1.0}
    assert set(summary["per_part"]) == {"handle", "top", "(whole object)"}
    assert summary["per_part"]["top"]["success_rate"] == 1.0
    report = results_markdown({"summary": summary, "config": EvalConfig(splits=("test1",)).identity(),
                               "label": "x", "complete": True, "resolved": {"step_limits": {"test1": 250}},
                               "provenance": {"date": "d", "git_sha": "s", "machine": "m"}})
    assert "| move_gripper | 2 | 1 | 50.00 |" in report
    assert summary["physics_unstable"] == 1 and "- 1 episodes ended early, failed, because their simulation" in report


def test_compare_pairs_two_runs_episode_by_episode(run_dir, tmp_path, capsys):
    """`partinstruct compare A B`: the episodes B gained and lost against A, with the exact McNemar p-value."""
    results = json.loads((run_dir / "results.json").read_text())
    template = results["episodes"][0]
    first = [template | {"ep_id": i, "split": "test1" if i < 20 else "test2", "success": i % 2 == 0}
             for i in range(30)]
    flipped = {1, 3, 5, 7, 21, 2}  # odd ids failed in A: 5 gained; 2 succeeded: 1 lost
    second = [r | {"success": not r["success"]} if r["ep_id"] in flipped else r for r in first]

    def write(name, records, **changes):
        path = tmp_path / name
        path.mkdir()
        (path / "results.json").write_text(json.dumps(results | {"episodes": records} | changes))
        return path

    a, b = write("a", first), write("b", second + [template | {"ep_id": 99}])
    capsys.readouterr()
    assert main(["compare", str(a), str(b), "--json", str(tmp_path / "c.json")]) == 0
    out = capsys.readouterr().out
    assert "30 episodes in both runs (0 only in A, 1 only in B, left out); B - A: +4 successes (5 gained, 1 lost, " \
           "p = 0.219)" in out
    assert "| Test 2 (OI) | 10 | 5 | 6 | 1 | 0 | 1 |" in out and "| test1 | 2 | mug_" in out
    comparison = json.loads((tmp_path / "c.json").read_text())
    assert comparison["overall"]["p_value"] == pytest.approx(14 / 64) and len(comparison["changed"]) == 6
    assert mcnemar_p(6, 9) == pytest.approx(9949 / 2 ** 14) and mcnemar_p(0, 0) == 1.0
    other = write("other", [r | {"obj_id": "mug_999"} if r["ep_id"] == 4 else r for r in second])
    assert main(["compare", str(a), str(other)]) == 2
    assert "episode 4 of test1 is not the same in both runs (obj_id" in capsys.readouterr().err
    task_mode = write("task", first, config=results["config"] | {"mode": "task"})
    assert main(["compare", str(a), str(task_mode)]) == 2
    assert "judge success differently" in capsys.readouterr().err
    assert main(["compare", str(a), str(tmp_path / "missing")]) == 2
    assert "no evaluation results at" in capsys.readouterr().err
    (tmp_path / "other.json").write_text("{}")
    assert main(["compare", str(a), str(tmp_path / "other.json")]) == 2
    assert "other.json is not a `partinstruct eval` results.json" in capsys.readouterr().err


def test_rerun_resumes_and_other_settings_are_refused(metadata, run_dir, capsys):
    before = json.loads((run_dir / "results.json").read_text())["episodes"]
    capsys.readouterr()
    assert run(metadata, run_dir) == 0
    out = capsys.readouterr().out
    assert "0 episodes run" in out and "2 resumed" in out and "| oracle (skill mode) |" in out
    assert json.loads((run_dir / "results.json").read_text())["episodes"] == before
    assert run(metadata, run_dir, "--seed", "3") == 2
    assert "other settings (seed: 0 there, 3 now)" in capsys.readouterr().err


def test_a_run_keeps_its_episodes_and_a_resume_reads_them_back(run_dir, tmp_path):
    """DIR/episodes.json holds the evaluated episodes (metadata schema). A resumed run of drawn episodes takes them
    from there, not from a new draw (which another machine or a code change could make differ); a new run draws.
    A run given that file as --metadata reads it and does not write over it."""
    evaluated = [r["ep_id"] for r in json.loads((run_dir / "results.json").read_text())["episodes"]]
    assert [e.ep_id for e in read_metadata(run_dir / "episodes.json")] == evaluated
    config = EvalConfig(policy="oracle", splits=("test1",), episodes_per_split=2, categories=("mug",))
    drawn = select_eval_episodes(config)
    kept = [replace(drawn[0], task_instruction="the instruction the first run drew")]
    write_metadata(kept, tmp_path / "episodes.json")
    assert _run_episodes(config, tmp_path, None, resuming=True) == (kept, True)
    assert _run_episodes(config, tmp_path, None, resuming=False) == (drawn, False)
    given = replace(config, metadata=str(tmp_path / "episodes.json"), episodes_per_split=None)
    assert _run_episodes(given, tmp_path, None, resuming=False) == (kept, True)


def test_outcomes_do_not_depend_on_the_workers(tmp_path):
    """Two mugs' episodes rolled out by one worker, by two (each object in its own thread, each thread with its
    own fork of the oracle and planner) and by two worker processes (each loading its own): the same records."""
    episodes = select_episodes("test1", 40, seed=0, categories=["mug"])
    per_mug = {}
    for episode in episodes:
        per_mug.setdefault(episode.obj_id, []).append(episode)
    chosen = [e for mine in [m for m in per_mug.values() if len(m) >= 2][:2] for e in mine[:2]]
    assert len(chosen) == 4
    write_metadata(chosen, tmp_path / "two_mugs.json")
    outcomes = []
    for option, number in (("--workers", 1), ("--workers", 2), ("--processes", 2)):
        out = tmp_path / f"{option[2:]}{number}"
        assert main(["eval", "--policy", "oracle", "--metadata", str(tmp_path / "two_mugs.json"), "--splits", "test1",
                     "--batch-size", "2", "--max-steps", "30", "--oracle-tries", "2", "--planner", "oracle",
                     option, str(number), "--out", str(out), "--quiet"]) == 0
        results = json.loads((out / "results.json").read_text())
        assert results["run"]["workers"] == number
        assert results["run"]["processes"] == (number if option == "--processes" else 1)
        outcomes.append(results["episodes"])
    assert outcomes[0] == outcomes[1] == outcomes[2]


@pytest.mark.parametrize("finished", [False, True])
def test_an_interrupted_run_says_what_it_kept(tmp_path, capsys, monkeypatch, finished):
    """Ctrl-C exits 130 and says whether finished batches were written (a run stopped before any says nothing was)."""
    out = tmp_path / "out"

    def interrupted(config, out_dir, progress):
        if finished:
            out_dir.mkdir()
            (out_dir / "results.json").write_text("{}")
        raise KeyboardInterrupt

    monkeypatch.setattr("partinstruct_mjx.eval.runner.evaluate", interrupted)
    assert main(["eval", "--policy", "oracle", "--out", str(out), "--quiet"]) == 130
    err = capsys.readouterr().err
    if finished:
        assert f"interrupted: finished batches are in {out / 'results.json'}; run the same command again" in err
    else:
        assert "interrupted: no batch had finished, nothing was written; run the same command again" in err


def test_objects_with_the_most_steps_to_run_go_first():
    """Workers take the object groups in order of their episodes' step limits summed (400 for test4, 250 else)."""
    from types import SimpleNamespace

    from partinstruct_mjx.eval.runner import _largest_first

    def episodes(*splits):
        return [SimpleNamespace(split=split) for split in splits]

    groups = {("mug", "a"): episodes("test1", "test1"), ("box", "b"): episodes("test4", "test4"),
              ("mug", "c"): episodes("test1", "test2", "test3"), ("box", "d"): episodes("test4")}
    assert [key for key, _ in _largest_first(groups)] == [("box", "b"), ("mug", "c"), ("mug", "a"), ("box", "d")]


def test_a_custom_policy_gets_the_skill_instructions(metadata, tmp_path):
    """The Python API with a policy object: a policy that holds still gets each scene's current skill instruction."""

    class Hold:
        def reset(self, env, state, key):
            self.seen = []

        def act(self, env, state, instructions, key):
            self.seen.append(list(instructions))
            return hold_action(state.obs["tcp_pose"])

    policy = Hold()
    config = EvalConfig(policy="hold", splits=("test1",), metadata=str(metadata), episodes_per_split=None,
                        batch_size=2, max_steps=4)
    results = evaluate(config, tmp_path / "hold", policy=policy, progress=False)
    episodes = results["episodes"]
    assert [r["success"] for r in episodes] == [False, False] and [r["steps"] for r in episodes] == [4, 4]
    assert [r["stopped_skill"] for r in episodes] == ["grasp_obj", "touch_obj"]
    assert len(policy.seen) == 4
    assert policy.seen[0][1].lower().startswith("touch")
    assert results["label"] == "hold (skill mode)"
    assert results["run"]["workers"] == 1, "a policy without fork() runs in one thread"
    with pytest.raises(EvalError, match=r"--workers 2 needs a policy and planner with fork\(\).*Hold has none"):
        evaluate(replace(config, workers=2), tmp_path / "hold2", policy=policy, progress=False)
    with pytest.raises(EvalError, match=r"--processes 2: each process loads the policy.*handed a policy object"):
        evaluate(replace(config, processes=2), tmp_path / "hold2", policy=policy, progress=False)
    assert not (tmp_path / "hold2").exists()


def test_a_run_with_processes_loads_its_policy_without_taking_the_gpu_memory(metadata, tmp_path, monkeypatch):
    """With worker processes the parent loads the policy (to check it) with JAX's GPU preallocation off, as the
    processes have it: a parent holding 75 % of the GPU left 16 processes of a trained policy out of memory."""
    from partinstruct_mjx.eval import runner
    from partinstruct_mjx.workers import PREALLOCATE

    monkeypatch.delenv(PREALLOCATE, raising=False)
    seen = []

    def load_and_stop(spec, tries):
        seen.append(os.environ.get(PREALLOCATE))
        raise EvalError("stop here")

    monkeypatch.setattr(runner, "load_policy", load_and_stop)
    config = EvalConfig(policy="oracle", splits=("test1",), metadata=str(metadata), episodes_per_split=None,
                        batch_size=2, processes=2)
    with pytest.raises(EvalError, match="stop here"):
        evaluate(config, tmp_path / "out", progress=False)
    assert seen == ["false"] and PREALLOCATE not in os.environ


def test_task_mode_with_the_oracle_planner(metadata, tmp_path):
    """Task mode judges the task's goals; the oracle planner and the per-skill records follow the skill chain."""
    out = tmp_path / "task"
    assert run(metadata, out, "--mode", "task", "--planner", "oracle", "--planner-every", "5") == 0
    results = json.loads((out / "results.json").read_text())
    assert results["config"]["planner"] == "oracle" and results["config"]["planner_every"] == 5
    assert results["resolved"]["env"]["skill_mode"] is False
    for record in results["episodes"]:
        assert record["success"] or record["steps"] == MAX_STEPS
        # Types 1 and 2: the task's goal (GRASPING / TOUCHING the part, on the table) includes the skill's effect.
        assert not record["success"] or record["skill_success"] == [True]


def test_oracle_planner_starts_at_the_first_skill(metadata):
    episodes = select_eval_episodes(EvalConfig(splits=("test1",), metadata=str(metadata), episodes_per_split=None))
    xml = assets_root() / "objects" / episodes[0].obj_class / episodes[0].obj_id / "object.xml"
    with PartInstructEnv(xml, 2, EnvConfig()) as env:
        state = env.reset(jax.random.PRNGKey(0), episodes)
        assert OraclePlanner().instructions(env, state, 0) == [e.skill_instructions[0] for e in episodes]
        assert OraclePlanner().instructions(env, state, 0) == env.instructions(state)


@pytest.mark.parametrize("argv, message", [
    (["--splits", "test9"], "unknown split 'test9'"),
    (["--policy", "/nonexistent/run"], "policy run directory not found: /nonexistent/run"),
    (["--planner-every", "4"], "--planner-every needs --planner"),
    (["--batch-size", "0"], "batch_size must be >= 1"),
    (["--episodes-per-split", "0"], "episodes_per_split must be >= 1"),
    (["--oracle-tries", "0"], "oracle_tries must be >= 1"),
    (["--workers", "0"], "workers must be >= 1"),
    (["--processes", "0"], "processes must be >= 1"),
    (["--workers", "2", "--processes", "2"], "workers (2) and processes (2): choose one"),
])
def test_bad_arguments_are_named(tmp_path, capsys, argv, message):
    args = ["eval", "--policy", "oracle", "--out", str(tmp_path / "out"), "--quiet", *argv]
    assert main(args) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_file_as_policy_or_out_is_refused(tmp_path, capsys):
    file = tmp_path / "file.txt"
    file.write_text("x")
    assert main(["eval", "--policy", str(file), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert "is not a directory" in capsys.readouterr().err
    assert main(["eval", "--policy", "oracle", "--out", str(file), "--quiet"]) == 2
    assert "is a file" in capsys.readouterr().err
    with pytest.raises(EvalError, match="unknown mode"):
        EvalConfig(mode="both")


def test_help_explains_policies_outputs_and_resume(command_help):
    text = command_help("eval")
    for phrase in ("--planner-every", "results.json", "resume", "load_policy", "test4"):
        assert phrase in text


@pytest.mark.slow
def test_mjx_backend_runs_the_same_evaluation(metadata, tmp_path):
    out = tmp_path / "mjx"
    assert main(["eval", "--policy", "oracle", "--metadata", str(metadata), "--splits", "test1", "--batch-size", "2",
                 "--max-steps", "10", "--backend", "mjx", "--out", str(out), "--quiet"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["config"]["backend"] == "mjx" and len(results["episodes"]) == 2
    assert all(r["steps"] <= 10 for r in results["episodes"])


def test_eval_bench_rates_and_projection():
    from partinstruct_mjx.bench import evaluation

    config = evaluation.bench_config(8, 16, oracle_tries=2, workers=3)
    assert config.splits == ("test1", "test2", "test3", "test4", "test5") and config.policy == "oracle"
    assert (config.oracle_tries, config.workers) == (2, 3)
    result = evaluation.EvalBenchResult(config, evaluation.EvalRun(40, 30, 300.0),
                                        [evaluation.EvalRun(40, 30, 60.0), evaluation.EvalRun(40, 30, 40.0)])
    assert result.episodes_per_min == pytest.approx(50.0)  # median of 40 and 60 episodes/min
    assert result.episodes_per_min_range == (40.0, 60.0)
    assert result.compile_s == pytest.approx(250.0)
    assert result.full_evaluation_min == pytest.approx(1800 / 50 + 250 / 60)
    text = evaluation.markdown([result], "cpu (cpu)", "off")
    assert "| 16 | 2 | 3 threads | 40 | 30 (75%) | 50.0 | 40.0 - 60.0 | 50.0 | 250.0 | 8.0 | 40.2 |" in text
    in_processes = evaluation.bench_config(8, 16, processes=16)
    assert (in_processes.workers, in_processes.processes) == (None, 16)
    assert evaluation.parallelism(in_processes) == "16 processes"
    trained = evaluation.EvalBenchResult(evaluation.bench_config(8, 16, policy="runs/dp3s"), result.cold, result.warm)
    text = evaluation.markdown([trained], "gpu (H100)", "on")
    assert text.startswith("`partinstruct eval --policy runs/dp3s`") and "| 16 | - | 2 threads |" in text
    # The full evaluation timed once (--repeats 0): the cold run's rate stands and is the projection.
    full = evaluation.EvalBenchResult(config, evaluation.EvalRun(1800, 1700, 450.0), [])
    assert full.episodes_per_min == pytest.approx(240.0) and full.full_evaluation_min == pytest.approx(7.5)
    text = evaluation.markdown([full], "gpu (H100)", "on")
    assert "| 1800 | 1700 (94%) | 240.0 | 240.0 - 240.0 | 450.0 | - | 240.0 | 7.5 |" in text
    assert "One cold run each" in text
