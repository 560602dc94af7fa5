"""Demonstration synthesis throughput: successful demos/hour, episodes/s, env steps/s and where the time goes.

Each batch size runs `synthesize` on the same episodes into fresh temporary directories: once cold (JAX's
in-process caches cleared, so it pays for compiling or loading from the persistent cache) and `repeats` times warm.
Rates are medians of the warm runs; the compile overhead is the cold run's wall time minus the warm median.
"""

from __future__ import annotations

import os
import tempfile
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from partinstruct_mjx.assets.partnet import category_slug
from partinstruct_mjx.tasks.episodes import Episode

BENCH_CATEGORIES = ("mug", "bottle")
DEFAULT_EPISODES = 256
"""Episodes per run: 128 per object, near a long run's share (a 64-episode run, whose objects' last scenes wait for
their slowest episode, measured 0.6x the demos/hour with 6 tries on a 2-core CPU; docs/benchmarks.md)."""


def bench_episodes(count: int, categories=BENCH_CATEGORIES, seed: int = 0) -> list[Episode]:
    """`count` train episodes (every task type, interleaved) on one object per category: the object most of the
    category's generated episodes use. Few objects keep the batches full, as in a long run (about 150 episodes
    per training object for 10,000 demos)."""
    from partinstruct_mjx.assets.catalog import load_catalog
    from partinstruct_mjx.data.synthesis import interleave
    from partinstruct_mjx.paths import assets_root
    from partinstruct_mjx.tasks.episodes import SEEN_TYPES, generate_episodes

    root = assets_root()
    catalog = [entry for entry in load_catalog(root) if entry["category"] in categories]
    objects_per_category = max(Counter(e["category"] for e in catalog if "train" in e["splits"]).values())
    per_type = -(-count * objects_per_category // (len(categories) * len(SEEN_TYPES)))
    episodes = generate_episodes(catalog, root, seed, per_type, ("train",))
    chosen = {}
    for category in categories:
        usage = Counter(e.obj_id for e in episodes if category_slug(e.obj_class) == category)
        chosen[category] = min(usage, key=lambda obj_id: (-usage[obj_id], obj_id))
    mine = [e for e in episodes if e.obj_id == chosen[category_slug(e.obj_class)]]
    return interleave(mine)[:count]


@dataclass(frozen=True)
class DemosResult:
    batch_size: int
    episodes: int
    objects: int
    cold: dict
    """The cold run's 'run' record (see synthesize)."""
    warm: list[dict]
    """The warm runs' records."""
    successes: int
    threads: int
    backend: str = "mujoco"
    oracle_tries: int | None = None
    """Tries per grasp or touch segment (oracle/backtrack.py)."""
    oracle_restarts: int | None = None
    """Times an episode whose tries all failed starts over (oracle/backtrack.py)."""
    workers: int = 1
    """Objects simulated at once (synthesize's threads)."""

    def _median(self, value) -> float:
        return float(np.median([value(run) for run in self.warm]))

    @property
    def demos_per_hour(self) -> float:
        return self._median(lambda r: r["successes"] / r["timing"]["wall_s"] * 3600)

    @property
    def demos_per_hour_range(self) -> tuple[float, float]:
        rates = [r["successes"] / r["timing"]["wall_s"] * 3600 for r in self.warm]
        return min(rates), max(rates)

    @property
    def episodes_per_s(self) -> float:
        return self._median(lambda r: r["processed"] / r["timing"]["wall_s"])

    @property
    def env_steps_per_s(self) -> float:
        """Steps of the episodes themselves (each up to its end) per second of simulation + oracle (seconds summed
        over the workers' threads)."""
        return self._median(lambda r: sum(b["steps"] for b in r["timing"]["batches"]) / r["timing"]["rollout_s"])

    @property
    def scene_steps_per_s(self) -> float:
        """Steps the scenes took for their episodes (backtracking's undone tries included) per second."""
        return self._median(lambda r: sum(b["scene_steps"] for b in r["timing"]["batches"]) / r["timing"]["rollout_s"])

    @property
    def clouds_per_s(self) -> float:
        return self._median(lambda r: sum(b["demo_steps"] for b in r["timing"]["batches"])
                            / max(r["timing"]["render_s"], 1e-9))

    def shares(self) -> dict[str, float]:
        """Median fraction of the wall time per phase."""
        return {phase: self._median(lambda r: r["timing"][f"{phase}_s"] / r["timing"]["wall_s"])
                for phase in ("rollout", "render", "write", "env")}

    @property
    def wall_s(self) -> float:
        return self._median(lambda r: r["timing"]["wall_s"])

    @property
    def compile_s(self) -> float:
        return self.cold["timing"]["wall_s"] - self.wall_s


def measure(episodes: list[Episode], batch_size: int, repeats: int, threads: int | None = None,
            sampler: str = "stride", backend: str = "mujoco", oracle_tries: int | None = None,
            workers: int | None = None, oracle_restarts: int | None = None) -> DemosResult:
    """One cold and `repeats` warm synthesis runs of `episodes` into temporary directories (`oracle_tries`,
    `oracle_restarts`, `workers`: None is `partinstruct demos`' default)."""
    import jax

    from partinstruct_mjx.data.synthesis import synthesize
    from partinstruct_mjx.oracle.backtrack import RESTARTS, SEGMENT_TRIES

    runs = []
    with tempfile.TemporaryDirectory(prefix="partinstruct-bench-demos-") as tmp:
        jax.clear_caches()
        for index in range(1 + repeats):
            summary = synthesize(episodes, Path(tmp) / f"run{index}", batch_size=batch_size, sampler=sampler,
                                 backend=backend, progress=False, num_threads=threads, oracle_tries=oracle_tries,
                                 workers=workers, oracle_restarts=oracle_restarts)
            runs.append(summary["run"])
    return DemosResult(batch_size, len(episodes), len({(e.obj_class, e.obj_id) for e in episodes}), runs[0], runs[1:],
                       runs[0]["successes"], threads or os.cpu_count() or 1, backend,
                       SEGMENT_TRIES if oracle_tries is None else oracle_tries,
                       RESTARTS if oracle_restarts is None else oracle_restarts, runs[0]["workers"])


def _backend(result: DemosResult) -> str:
    return ("`mjx` backend (physics on the JAX device)" if result.backend == "mjx"
            else f"`mujoco` backend with {result.threads} threads")


def markdown(results: list[DemosResult], episodes: list[Episode], device: str, cache: str) -> str:
    types = sorted({e.task_type for e in episodes})
    objects = sorted({e.obj_id for e in episodes})
    rows = []
    for r in results:
        shares = r.shares()
        low, high = r.demos_per_hour_range
        rows.append(
            f"| {r.batch_size} | {r.oracle_tries} | {r.oracle_restarts} | {r.workers} | {r.episodes} | "
            f"{r.successes} ({r.successes / r.episodes:.0%}) | "
            f"{r.demos_per_hour:,.0f} | {low:,.0f} - {high:,.0f} | {r.episodes_per_s:.2f} | {r.env_steps_per_s:,.0f} | "
            f"{r.scene_steps_per_s:,.0f} | {r.clouds_per_s:,.0f} | {r.wall_s:.1f} | {shares['rollout']:.0%} / "
            f"{shares['render']:.0%} / {shares['write']:.0%} / {shares['env']:.0%} | {r.compile_s:.1f} | "
            f"{r.cold['successes'] / r.cold['timing']['wall_s'] * 3600:,.0f} |")
    repeats = len(results[0].warm) if results else 0
    return (
        f"`partinstruct demos` on {len(episodes)} train episodes (task types {types[0]}-{types[-1]}, interleaved) on "
        f"{', '.join(objects)}, seed 0, stride-sampled clouds, {_backend(results[0])}, "
        f"JAX on {device}; JAX persistent compilation cache: {cache}. Few objects keep batches full, as in a long "
        f"run; a run spread over every training object compiles once per batch size (the built-in objects share "
        f"their array shapes). Rates are "
        f"medians of {repeats} warm run(s) (one by default: a run takes minutes); 'compile' is the cold run's wall "
        f"time (in-process JAX caches cleared) minus the warm median, and the last column is the cold run's rate.\n\n"
        "| batch | oracle tries | restarts | workers | episodes | demos (oracle success) | demos/hour | range | "
        "episodes/s | env steps/s | scene steps/s | clouds/s | wall s | simulation+oracle / clouds / writing / envs | compile s | "
        "cold demos/hour |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n\n"
        "'workers' are the objects simulated at once, each in a thread with its own env and its share of the "
        "physics threads (`partinstruct demos --workers`); clouds and writing run in one more thread beside them, "
        "so the phases' shares of the wall time add up to more than 100 %. "
        "env steps/s counts each episode's own steps (those of its final demo or failure) per second of "
        "simulation+oracle (a worker's seconds: the seconds are summed over the workers); 'oracle tries' are its "
        "tries per grasp or touch (1: no backtracking; `partinstruct demos --oracle-tries`), 'restarts' the "
        "times an episode whose tries all failed starts over (`--oracle-restarts`; none with one try); scene "
        "steps/s counts every step a scene took for an episode, the "
        "tries that the oracle's backtracking undid included (scenes are streamed: one whose episode ended takes "
        "the next; at the end of an object's episodes the idle scenes are not counted).\n")
