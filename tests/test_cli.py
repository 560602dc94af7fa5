"""The command line: help, the main job, and the benchmark writer."""

import os
import subprocess
import sys

import pytest

from partinstruct_mjx.bench.report import write_section
from partinstruct_mjx.cli import main


def test_help_lists_the_commands():
    out = subprocess.run([sys.executable, "-m", "partinstruct_mjx.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    assert "simulate" in out.stdout and "bench" in out.stdout


def test_simulate_main_job_reports_held_objects(capsys):
    assert main(["simulate", "--batch", "2", "--seed", "5"]) == 0
    out = capsys.readouterr().out
    assert "2/2 objects lifted and held for 3 s" in out


def test_simulate_reports_a_missing_object_clearly(tmp_path, capsys):
    assert main(["simulate", "--object", str(tmp_path / "missing.xml")]) == 2
    assert "missing.xml" in capsys.readouterr().err


def test_bench_writes_its_section_and_keeps_others(tmp_path, capsys):
    report = tmp_path / "benchmarks.md"
    write_section(report, "other", "## Other\n\nkeep me")
    assert main(["bench", "--batch-sizes", "1", "2", "--steps", "5", "--repeats", "1", "--output", str(report)]) == 0
    text = report.read_text()
    assert "keep me" in text and "## CPU backend" in text
    assert "| 2 |" in text and "command: `partinstruct bench" in text
    assert main(["bench", "--batch-sizes", "1", "--steps", "5", "--repeats", "1", "--output", str(report)]) == 0
    assert report.read_text().count("## CPU backend") == 1


@pytest.mark.slow
def test_bench_demos_keeps_the_rows_of_a_run_stopped_midway(tmp_path, monkeypatch):
    """The demos suite rewrites its section after every row: a run interrupted during its second row (a device
    call's time limit) leaves the first one written."""
    from partinstruct_mjx.bench import demos
    from partinstruct_mjx.oracle import backtrack

    real_measure, calls = demos.measure, []

    def measure_then_stop(*args, **kwargs):
        calls.append(kwargs["oracle_tries"])
        if len(calls) > 1:
            raise KeyboardInterrupt
        return real_measure(*args, **kwargs)

    monkeypatch.setattr(demos, "measure", measure_then_stop)
    report = tmp_path / "benchmarks.md"
    with pytest.raises(KeyboardInterrupt):
        main(["bench", "demos", "--episodes", "2", "--batch-sizes", "2", "--oracle-tries", "1", "4",
              "--output", str(report)])
    assert calls == [1, 4]
    rows = [line for line in report.read_text().splitlines() if line.startswith("| 2 |")]
    assert len(rows) == 1 and rows[0].startswith(f"| 2 | 1 | {backtrack.RESTARTS} | 2 |")
    # A CPU run's section names the core count: a GPU machine's cores with JAX on the CPU get a section of their own.
    assert f"<!-- bench:demos_cpu{os.cpu_count()} -->" in report.read_text()


def test_bench_eval_with_processes_leaves_the_gpu_to_them(tmp_path, monkeypatch):
    """The eval suite measuring worker processes runs with JAX's GPU preallocation off in the bench's own process,
    which names the device before the processes start: preallocating there took 75 % of the GPU from them."""
    from partinstruct_mjx.bench import evaluation
    from partinstruct_mjx.workers import PREALLOCATE

    monkeypatch.delenv(PREALLOCATE, raising=False)
    seen = []

    def measure_and_stop(config, repeats, on_run=None):
        seen.append((config.processes, os.environ.get(PREALLOCATE)))
        raise KeyboardInterrupt

    monkeypatch.setattr(evaluation, "measure", measure_and_stop)
    for processes in ([], ["--processes", "2"]):
        with pytest.raises(KeyboardInterrupt):
            main(["bench", "eval", "--episodes", "1", *processes, "--output", str(tmp_path / "benchmarks.md")])
    assert seen == [(1, None), (2, "false")] and PREALLOCATE not in os.environ


def test_bench_times_the_cold_run_alone_only_in_the_eval_suite(tmp_path, capsys):
    """--repeats 0 (the full evaluation timed once) is the eval suite's; the demos suite needs a warm run."""
    assert main(["bench", "demos", "--repeats", "0", "--output", str(tmp_path / "benchmarks.md")]) == 2
    assert "--repeats 0: the demos suite needs at least 1" in capsys.readouterr().err
    assert not (tmp_path / "benchmarks.md").exists()


@pytest.mark.parametrize("command", ["demos", "eval"])
def test_help_states_the_oracle_tries_the_command_uses(command):
    from partinstruct_mjx.oracle.backtrack import SEGMENT_TRIES

    out = subprocess.run([sys.executable, "-m", "partinstruct_mjx.cli", command, "--help"], capture_output=True,
                         text=True)
    assert out.returncode == 0
    assert f"(default {SEGMENT_TRIES}, oracle/backtrack.py's SEGMENT_TRIES" in " ".join(out.stdout.split())


def test_demos_help_states_the_oracle_restarts_it_uses():
    from partinstruct_mjx.oracle.backtrack import RESTARTS

    out = subprocess.run([sys.executable, "-m", "partinstruct_mjx.cli", "demos", "--help"], capture_output=True,
                         text=True)
    assert out.returncode == 0
    assert f"(default {RESTARTS}, oracle/backtrack.py's RESTARTS" in " ".join(out.stdout.split())
