"""Evaluation throughput: episodes/minute of `partinstruct eval` (the oracle, or a training run's policy) over the
five test splits.

One cold run (JAX's in-process caches cleared, so it pays for compiling or loading from the persistent cache) and
`repeats` warm runs of the same evaluation into temporary directories; each run's wall time covers what
`partinstruct eval` does (episode generation, environments, rollouts, results files). Rates are medians of the warm
runs; the compile overhead is the cold run's wall time minus the warm median. With no warm runs (`repeats` 0: the
full evaluation's 1,800 episodes take minutes a run) the cold run's rate stands and no compile time is split off.

The projection to 1,800 episodes scales the episodes. A rollout's time goes with its batches (one per object and
split, each run to its slowest scene), and a trained policy on the GPU costs about the same per batch whatever its
size, so a small draw (one or two episodes per batch) overstates its full evaluation several times; run the full
evaluation itself (`--episodes 360 --repeats 0`) for that.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from partinstruct_mjx.eval.config import ORACLE, TEST_SPLITS, EvalConfig
from partinstruct_mjx.oracle.backtrack import SEGMENT_TRIES
from partinstruct_mjx.workers import default_workers

FULL_EVALUATION = 1800
"""Episodes of the full evaluation the DESIGN.md target times (< 10 minutes on one H100)."""


@dataclass(frozen=True)
class EvalRun:
    episodes: int
    successes: int
    wall_s: float


@dataclass(frozen=True)
class EvalBenchResult:
    config: EvalConfig
    cold: EvalRun
    warm: list[EvalRun]

    def _timed(self) -> list[EvalRun]:
        """The runs the rate comes from: the warm ones, or the cold one alone."""
        return self.warm or [self.cold]

    def _rates(self) -> list[float]:
        """Episodes/min of each timed run."""
        return [r.episodes / r.wall_s * 60 for r in self._timed()]

    @property
    def episodes_per_min(self) -> float:
        return float(np.median(self._rates()))

    @property
    def episodes_per_min_range(self) -> tuple[float, float]:
        return min(self._rates()), max(self._rates())

    @property
    def compile_s(self) -> float:
        return self.cold.wall_s - self.wall_s

    @property
    def wall_s(self) -> float:
        """Median wall time of the timed runs."""
        return float(np.median([r.wall_s for r in self._timed()]))

    @property
    def full_evaluation_min(self) -> float:
        """Minutes FULL_EVALUATION episodes take at the warm rate, plus the compile overhead once."""
        return FULL_EVALUATION / self.episodes_per_min + self.compile_s / 60


def measure(config: EvalConfig, repeats: int, on_run=None) -> EvalBenchResult:
    """One cold and `repeats` warm evaluations with `config`; `on_run(index, run)` sees each run as it
    ends (index 0 is the cold one), so a stopped benchmark still shows what it measured."""
    import jax

    from partinstruct_mjx.eval.runner import evaluate

    runs = []
    with tempfile.TemporaryDirectory(prefix="partinstruct-bench-eval-") as tmp:
        jax.clear_caches()
        for index in range(1 + repeats):
            start = time.perf_counter()
            results = evaluate(config, Path(tmp) / f"run{index}", progress=False)
            wall = time.perf_counter() - start
            outcomes = results["episodes"]
            runs.append(EvalRun(len(outcomes), sum(bool(e["success"]) for e in outcomes), wall))
            if on_run is not None:
                on_run(index, runs[-1])
    return EvalBenchResult(config, runs[0], runs[1:])


def bench_config(episodes_per_split: int, batch_size: int, backend: str = "mujoco", threads: int | None = None,
                 oracle_tries: int | None = None, workers: int | None = None, processes: int = 1,
                 policy: str = ORACLE) -> EvalConfig:
    """`policy` ('oracle' or a training run directory) on every test split, skill mode, `episodes_per_split`
    generated episodes each (seed 0)."""
    return dataclasses.replace(EvalConfig(), policy=policy, splits=TEST_SPLITS, episodes_per_split=episodes_per_split,
                               batch_size=batch_size, backend=backend, num_threads=threads, oracle_tries=oracle_tries,
                               workers=workers, processes=processes)


def oracle_tries(config: EvalConfig) -> int | None:
    """The oracle's tries per grasp or touch in a run of `config`; None for a trained policy."""
    if config.policy != ORACLE:
        return None
    return SEGMENT_TRIES if config.oracle_tries is None else config.oracle_tries


def parallelism(config: EvalConfig) -> str:
    """How a run rolls objects out at once: 'N threads' or 'N processes'."""
    if config.processes > 1:
        return f"{config.processes} processes"
    threads = default_workers(config.backend) if config.workers is None else config.workers
    return f"{threads} thread{'s' if threads > 1 else ''}"


def _timing(warm_runs: int) -> str:
    """How the table's rate and compile time were taken."""
    if not warm_runs:
        return "One cold run each (in-process JAX caches cleared): its rate stands; no compile time is split off."
    return (f"Rates are medians of {warm_runs} warm run(s); 'compile' is the cold run's wall time (in-process JAX "
            f"caches cleared) minus the warm median.")


def markdown(results: list[EvalBenchResult], device: str, cache: str) -> str:
    first = results[0].config
    rows = []
    for r in results:
        low, high = r.episodes_per_min_range
        successes = r.cold.successes
        tries = oracle_tries(r.config) or "-"
        rows.append(f"| {r.config.batch_size} | {tries} | {parallelism(r.config)} | {r.cold.episodes} | "
                    f"{successes} ({successes / r.cold.episodes:.0%}) | {r.episodes_per_min:,.1f} | {low:,.1f} - {high:,.1f} | "
                    f"{r.wall_s:.1f} | {f'{r.compile_s:.1f}' if r.warm else '-'} | "
                    f"{r.cold.episodes / r.cold.wall_s * 60:,.1f} | {r.full_evaluation_min:,.1f} |")
    threads = first.num_threads or os.cpu_count() or 1
    return (
        f"`partinstruct eval --policy {first.policy}` ({first.mode} mode) on {first.episodes_per_split} generated "
        f"episodes of each of {', '.join(first.splits)} (seed {first.seed}), `{first.backend}` backend"
        f"{f' with {threads} physics threads shared by the workers' if first.backend == 'mujoco' else ''}, "
        f"JAX on {device}; "
        f"JAX persistent "
        f"compilation cache: {cache}. Each run's wall time is the whole evaluation (episode generation, one "
        f"environment per object and batch size, rollouts to success or the step limit, results files). "
        f"{_timing(len(results[0].warm))} The last column projects {FULL_EVALUATION:,} episodes (the "
        f"DESIGN.md target: < 10 minutes on one H100) at that rate plus the compile once"
        f"{'; a trained policy adds its own inference to every step' if first.policy == ORACLE else ''}. "
        f"Worker processes start afresh in every run (imports, tracing), so their warm runs pay what the threads' cold "
        f"run does, less the persistent cache's compiles. A run's time goes with its batches (one per object and "
        f"split) more than with its episodes, so the projection from a small draw overstates a trained policy's full "
        f"evaluation (run it with --episodes 360 --repeats 0).\n\n"
        "| batch | oracle tries | workers | episodes | success | episodes/min | range | wall s | "
        f"compile s | cold episodes/min | {FULL_EVALUATION:,} episodes, min |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
