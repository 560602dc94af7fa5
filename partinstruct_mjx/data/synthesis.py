"""Demonstration synthesis: run the oracle on episodes, render point clouds of the successes, store them.

`synthesize` groups episodes by object (one env per object, of `batch_size` scenes or the power of two that holds a
smaller group), streams the object's episodes through it with `run_oracle` (a scene whose episode ended takes the
next one), renders the static camera's clouds of every successful episode's steps with the JAX point renderer and
commits every `batch_size` finished episodes to a `DemoWriter` run directory, so an interrupted run resumes where
it stopped. `select_episodes` picks the episodes the CLI asks for (a count spread over task types and categories of
a split, or a metadata file).

Reproducibility: every random draw derives from the seed and the episode's own seed or ep_id (the oracle's and the
clouds'), and the C backend steps each scene independently, so at one batch size an episode's demo depends
neither on its scene nor on the episodes beside it: the same episodes with the same batch size, seed and sampler
give the same demos however often the run was interrupted. (Another batch size can change the last bits of the
oracle's float32 arithmetic, and with them a demo's details.)
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import threading
import time
from collections import Counter
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.assets.catalog import load_catalog
from partinstruct_mjx.assets.partnet import category_slug
from partinstruct_mjx.errors import DataError, TaskError
from partinstruct_mjx.paths import assets_root
from partinstruct_mjx.tasks.episodes import (SPLIT_ID_STRIDE, SPLIT_TYPES, SPLITS, Episode, generate_episodes,
                                             read_metadata, validate_episodes, write_metadata)
from partinstruct_mjx.workers import default_workers, process_pool, run_in_threads, threads_per_worker

ALL_TYPES = "all-types"
"""Pseudo-split: train for task types 1-10 plus test4 for 11-16 (every type once, for a per-type table)."""
SAMPLERS = ("stride", "fps")
RENDER_CHUNK = 64
"""Clouds rendered per call of the jitted renderer (the last chunk is padded, so it compiles once)."""
ENV_NAME = "PartInstructMJX"
SELECTIONS_DIR = "selections"
"""Run-directory folder of generated episode selections (`remembered_selection`)."""


def env_args(backend: str = "mujoco", sampler: str = "stride", seed: int = 0, oracle_tries: int | None = None,
             oracle_restarts: int | None = None) -> dict:
    """The robomimic-style env_args of a run directory; a resumed run must match them (DemoWriter checks).
    `oracle_tries`: tries per grasp or touch segment (oracle/backtrack.py; None: its SEGMENT_TRIES);
    `oracle_restarts`: times an episode every try failed starts over (None: backtrack.RESTARTS; none with one try)."""
    from partinstruct_mjx.env import STEP_LIMIT, STEP_LIMIT_TEST4
    from partinstruct_mjx.oracle.backtrack import RESTARTS, SEGMENT_TRIES

    return {"env_name": ENV_NAME, "type": "partinstruct_mjx",
            "env_kwargs": {"backend": backend, "skill_mode": False, "rotation": "euler", "control_freq": 20,
                           "step_limit": STEP_LIMIT, "step_limit_test4": STEP_LIMIT_TEST4},
            "synthesis": {"oracle": "partinstruct_mjx.oracle", "seed": seed,
                          "oracle_tries": SEGMENT_TRIES if oracle_tries is None else oracle_tries,
                          "oracle_restarts": RESTARTS if oracle_restarts is None else oracle_restarts,
                          "pcd_sampler": sampler,
                          "pcd_camera": "agentview", "pcd_size": 1024}}


@dataclass
class Timing:
    """Seconds per phase, accumulated over a run, and one record per batch (the first holds the compiles). Clouds and
    writing run in a thread beside the simulation of the next batch, so the phases may add up to more than wall_s."""

    env_s: float = 0.0
    """Building envs (scene compile, part geometry), one per object."""
    rollout_s: float = 0.0
    """run_oracle: reset, physics, IK, predicates and the oracle (including their JIT compiles)."""
    render_s: float = 0.0
    """Point clouds of the successful episodes (including the renderer's compile)."""
    write_s: float = 0.0
    """DemoWriter.add of every batch and the final merge (finalize)."""
    wall_s: float = 0.0
    batches: list[dict] = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


def synthesize(episodes: list[Episode], out_dir: str | os.PathLike, batch_size: int = 16, seed: int = 0,
               sampler: str = "stride", backend: str = "mujoco", progress: bool = True,
               assets: str | os.PathLike | None = None, num_threads: int | None = None,
               render_chunk: int = RENDER_CHUNK, oracle_tries: int | None = None, workers: int | None = None,
               oracle_restarts: int | None = None) -> dict:
    """Run the oracle on `episodes` (skipping those already committed in `out_dir`) and store the successful demos.

    Returns the run directory's summary (see DemoWriter.finalize) plus 'run': this call's counts and its Timing.
    On KeyboardInterrupt the committed batches are finalized before the interrupt is re-raised. A demo's
    initial_state is the MuJoCo physics state after reset; the mjx backend has none, so there it is the first
    step's joint_states, gripper_state and object_pose. `oracle_tries`, `oracle_restarts`: see `env_args`.
    `workers`: objects
    simulated at once, each in its own thread and env with `num_threads` (default: the cores) // workers physics
    threads (None: `default_workers`); a run's demos do not depend on it.
    """
    from tqdm import tqdm

    from partinstruct_mjx.data.demos import DemoWriter

    if batch_size < 1:
        raise DataError(f"batch_size must be >= 1, got {batch_size}")
    if sampler not in SAMPLERS:
        raise DataError(f"unknown point-cloud sampler '{sampler}'; expected one of {', '.join(SAMPLERS)}")
    if oracle_tries is not None and oracle_tries < 1:
        raise DataError(f"oracle_tries must be >= 1, got {oracle_tries}")
    if oracle_restarts is not None and oracle_restarts < 0:
        raise DataError(f"oracle_restarts must be >= 0, got {oracle_restarts}")
    if workers is not None and workers < 1:
        raise DataError(f"workers must be >= 1, got {workers}")
    counts = Counter(e.ep_id for e in episodes)
    repeated = sorted(ep_id for ep_id, n in counts.items() if n > 1)
    if repeated:
        raise DataError(f"episode {repeated[0]} is given more than once")
    root = Path(assets) if assets is not None else assets_root()
    objects = object_paths(episodes, root)
    args = env_args(backend, sampler, seed, oracle_tries, oracle_restarts)
    writer = DemoWriter(out_dir, args)
    done = writer.finished_ids()
    todo = [e for e in episodes if e.ep_id not in done]
    groups = object_groups(todo)

    timing = Timing()
    start = time.perf_counter()
    tally = Counter()
    bar = tqdm(total=len(todo), desc="demos", unit="episode", disable=not progress or not todo)
    lock = threading.Lock()
    workers = max(1, min(workers or default_workers(backend), len(groups)))
    threads_each = threads_per_worker(num_threads, workers)

    def counted(future) -> None:
        """Wait for a committed batch and count it."""
        record = future.result()
        with lock:
            timing.batches.append(record)
            for phase in ("env_s", "rollout_s", "render_s", "write_s"):
                setattr(timing, phase, getattr(timing, phase) + record[phase])
            tally.update(processed=record["episodes"], successes=record["successes"])
            elapsed = time.perf_counter() - start
            bar.set_postfix(demos_per_s=f"{tally['successes'] / elapsed:.2f}",
                            success=f"{tally['successes'] / tally['processed']:.0%}", refresh=False)
            bar.update(record["episodes"])

    def simulate(slot: int, group, stop: threading.Event) -> None:
        """Simulate one object's episodes (until the run stops); commit each finished batch."""
        key, mine = group
        worker = _ObjectWorker(objects[key], _bucket(len(mine), batch_size), backend, threads_each,
                               args["synthesis"]["oracle_tries"], args["synthesis"]["oracle_restarts"])
        pending = None
        try:
            for batch in worker.run(mine, jax.random.PRNGKey(seed), sampler, render_chunk, stop):
                if pending is not None:
                    counted(pending)
                pending = committer.submit(worker.commit, batch, writer)
        finally:
            worker.close()
            if pending is not None:
                counted(pending)

    # `workers` threads simulate objects at once; one thread renders and writes finished batches beside them.
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="partinstruct-demos-commit") as committer:
        try:
            run_in_threads(groups.items(), workers, simulate, "partinstruct-demos-sim")
        except BaseException:
            bar.close()
            committer.shutdown(wait=True)
            writer.finalize()
            raise
    bar.close()
    tick = time.perf_counter()
    summary = writer.finalize()
    timing.write_s += time.perf_counter() - tick
    timing.wall_s = time.perf_counter() - start
    summary["run"] = {"requested": len(episodes), "already_done": len(episodes) - len(todo),
                      "processed": tally["processed"], "successes": tally["successes"], "batch_size": batch_size,
                      "workers": workers, "timing": timing.as_dict()}
    return summary


def _bucket(count: int, batch_size: int) -> int:
    """Env batch size for `count` episodes: the next power of two, at most `batch_size`. Every new batch size compiles
    the oracle and env step again (objects share the shapes), so sizes are few; the rest is padding."""
    return min(batch_size, 1 << (count - 1).bit_length())


def object_groups(items: list, episode_of=lambda item: item) -> dict[tuple[str, str], list]:
    """Items (episodes, or records holding one: `episode_of`) per object (category, obj_id), in (category, obj_id,
    ep_id) order: one env serves each group."""
    def key(item):
        episode = episode_of(item)
        return category_slug(episode.obj_class), episode.obj_id

    groups: dict[tuple[str, str], list] = {}
    for item in sorted(items, key=lambda item: (*key(item), episode_of(item).ep_id)):
        groups.setdefault(key(item), []).append(item)
    return groups


def object_batches(episodes: list[Episode], batch_size: int) -> list[tuple[list[Episode], int]]:
    """One object's episodes in batches of at most `batch_size`, each with the env size it runs in (`_bucket`)."""
    batches = [episodes[first:first + batch_size] for first in range(0, len(episodes), batch_size)]
    return [(batch, _bucket(len(batch), batch_size)) for batch in batches]


def pad_batch(batch: list, size: int) -> list:
    """`batch` repeated cyclically to `size` entries, so a short batch fills an env of that size."""
    return [batch[i % len(batch)] for i in range(size)]


def object_paths(episodes: list[Episode], root: Path) -> dict[tuple[str, str], Path]:
    """(category, obj_id) -> object.xml of every episode's object; TaskError for one the catalog lacks."""
    catalog = {(entry["category"], entry["id"]): root / entry["path"] / "object.xml" for entry in load_catalog(root)}
    paths = {}
    for episode in episodes:
        key = (category_slug(episode.obj_class), episode.obj_id)
        if key not in catalog:
            raise TaskError(f"episode {episode.ep_id}: object {key[0]}/{key[1]} is not in {root}/catalog.json")
        paths[key] = catalog[key]
    return paths


@dataclass(frozen=True)
class _Finished:
    """Episodes the oracle finished (OracleEpisode records), waiting to be rendered and written."""

    runs: list
    episodes: list[Episode]
    """The object's episodes (`runs[i].index` indexes them)."""
    cloud_key: jax.Array
    sampler: str
    chunk: int
    env_s: float
    rollout_s: float


class _ObjectWorker:
    """One env (and point-cloud surface) of one object and batch size, reused for all its batches."""

    def __init__(self, object_xml: Path, batch_size: int, backend: str, num_threads: int | None, oracle_tries: int,
                 oracle_restarts: int):
        from partinstruct_mjx.env import EnvConfig, PartInstructEnv
        from partinstruct_mjx.obs import point_renderer
        from partinstruct_mjx.obs.cameras import AGENTVIEW, scene_camera

        tick = time.perf_counter()
        self.batch_size = batch_size
        self.oracle_tries, self.oracle_restarts = oracle_tries, oracle_restarts
        self.env = PartInstructEnv(object_xml, batch_size,
                                   EnvConfig(backend=backend, skill_mode=False, num_threads=num_threads))
        self.surface = point_renderer.surface_points(self.env.scene, self.env.geometry)
        self.camera = scene_camera(self.env.scene, AGENTVIEW)
        self.env_s = time.perf_counter() - tick  # building the env, reported with the first batch

    def close(self) -> None:
        self.env.close()

    def run(self, episodes: list[Episode], key: jax.Array, sampler: str, chunk: int, stop: threading.Event):
        """Stream one object's episodes through the env (a scene whose episode ended takes the next); yield every
        `batch_size` finished episodes (the last chunk may be shorter) as a `_Finished` for `commit`. Returns early
        once `stop` is set."""
        from partinstruct_mjx.oracle.rollout import run_oracle

        rollout_key, cloud_key = jax.random.split(key)
        finished, ended = [], 0
        tick = time.perf_counter()
        for episode in run_oracle(self.env, episodes, rollout_key, record=True, tries=self.oracle_tries,
                                  restarts=self.oracle_restarts):
            if stop.is_set():
                return
            finished.append(episode)
            ended += 1
            if len(finished) < self.batch_size and ended < len(episodes):
                continue
            rollout_s = time.perf_counter() - tick
            yield _Finished(finished, episodes, cloud_key, sampler, chunk, self.env_s, rollout_s)
            self.env_s = 0.0
            finished = []
            tick = time.perf_counter()

    def commit(self, batch: _Finished, writer) -> dict:
        """Render the clouds of `batch`'s demos, add its demos and failures to `writer`; return the batch's record
        (counts and timings). Uses only the worker's surface and camera: it may run after `close`."""
        from partinstruct_mjx.data.demos import Demo

        finished, episodes = batch.runs, batch.episodes
        # A skill the oracle failed ends the episode; only an episode whose oracle never failed is a demo.
        is_demo = [r.success and r.failed_skill < 0 and r.length > 0 for r in finished]
        winners = [r for r, demo in zip(finished, is_demo) if demo]
        tick = time.perf_counter()
        clouds = self._clouds(winners, [episodes[r.index].ep_id for r in winners], batch.cloud_key, batch.sampler,
                              batch.chunk)
        render_s = time.perf_counter() - tick
        demos = []
        for r, cloud in zip(winners, clouds):
            obs = {"agentview_pcd": cloud[..., :3], "agentview_part_pcd": cloud}
            obs |= {name: r.obs[name] for name in ("tcp_pose", "joint_states", "gripper_state", "object_pose")}
            state = r.initial_state if r.initial_state is not None else np.concatenate(
                [r.obs[name][0] for name in ("joint_states", "gripper_state", "object_pose")])
            demos.append(Demo(episodes[r.index], r.actions, obs, r.skill_index, state))
        failures = [(episodes[r.index], _failure_name(episodes[r.index], r.failed_skill, r.length, r.unstable))
                    for r, demo in zip(finished, is_demo) if not demo]
        tick = time.perf_counter()
        writer.add(demos, failures)
        write_s = time.perf_counter() - tick
        return {"object": episodes[0].obj_id, "category": category_slug(episodes[0].obj_class),
                "episodes": len(finished), "successes": len(demos),
                "steps": int(sum(r.length for r in finished)), "demo_steps": int(sum(r.length for r in winners)),
                "scene_steps": int(sum(r.simulated_steps for r in finished)),
                "env_s": batch.env_s, "rollout_s": batch.rollout_s, "render_s": render_s, "write_s": write_s}

    def _clouds(self, runs: list, ep_ids: list[int], key: jax.Array, sampler: str,
                chunk: int) -> list[np.ndarray]:
        """(T, 1024, 4) agentview_part_pcd of each recorded OracleEpisode in `runs`, rendered in fixed-size chunks of
        steps."""
        from partinstruct_mjx.obs import point_renderer

        if not runs:
            return []
        pos = np.concatenate([r.body_pos for r in runs])
        quat = np.concatenate([r.body_quat for r in runs])
        mask = np.concatenate([r.target_mask for r in runs])
        keys = np.concatenate([np.asarray(jax.random.split(jax.random.fold_in(key, ep_id), r.length))
                               for r, ep_id in zip(runs, ep_ids)])
        out = []
        for first in range(0, len(pos), chunk):
            part = slice(first, first + chunk)
            n = len(pos[part])
            cloud = point_renderer.render_batch(
                self.surface, self.camera, jnp.asarray(_pad(pos[part], chunk)), jnp.asarray(_pad(quat[part], chunk)),
                jnp.asarray(_pad(mask[part], chunk)), jnp.asarray(_pad(keys[part], chunk)), sampler=sampler)
            out.append(np.concatenate([np.asarray(cloud.points)[:n], np.asarray(cloud.target)[:n, :, None]], -1))
        clouds = np.concatenate(out).astype(np.float32)
        return np.split(clouds, np.cumsum([r.length for r in runs])[:-1])


def _pad(rows: np.ndarray, size: int) -> np.ndarray:
    """`rows` extended to `size` rows by repeating its last row."""
    return rows if len(rows) == size else np.concatenate([rows, np.repeat(rows[-1:], size - len(rows), 0)])


def _failure_name(episode: Episode, failed_skill: int, length: int, unstable: bool) -> str:
    """Why an episode is not a demo: the chain skill the oracle failed, 'physics_unstable' (the simulation
    diverged), 'step_limit', or 'no_task_success' (the oracle executed the whole chain but the task's goals did not
    hold)."""
    if 0 <= failed_skill < len(episode.chain):
        return episode.chain[failed_skill].name
    if unstable:
        return "physics_unstable"
    from partinstruct_mjx.env import step_limit

    return "step_limit" if length >= step_limit(episode.split) else "no_task_success"


# --- choosing episodes ------------------------------------------------------------------------------------------


def split_types(split: str) -> dict[str, tuple[int, ...]]:
    """split -> its task types; 'all-types' is train (1-10) plus test4 (11-16). TaskError for an unknown split."""
    if split == ALL_TYPES:
        return {"train": SPLIT_TYPES["train"], "test4": SPLIT_TYPES["test4"]}
    if split not in SPLITS:
        raise TaskError(f"unknown split '{split}'; expected one of {', '.join(SPLITS)} or {ALL_TYPES}")
    return {split: SPLIT_TYPES[split]}


def select_episodes(split: str | None = "train", count: int | None = None, seed: int = 0,
                    types: list[int] | None = None, categories: list[str] | None = None,
                    metadata: str | os.PathLike | None = None,
                    assets: str | os.PathLike | None = None, pool: Executor | None = None) -> list[Episode]:
    """The episodes a synthesis run works on, in a deterministic order that interleaves task types and categories.

    Without `metadata`, episodes are generated (seeded, like `partinstruct episodes`) with just enough per
    (split, category, type) for `count`; with it, the file's episodes are used (`split` None keeps all). `types`
    and `categories` filter; `count` keeps the first episodes of the interleaved order (every selected type is
    represented once count >= #types). Only the wanted (category, type) cells are drawn, with the ids and draws they
    have when the whole catalog is, and numbered draw-first (see `_renumbered`), so an episode keeps its ep_id
    whatever the filters and the count. With a process `pool`, each category's episodes are drawn in one of its
    processes (every draw is seeded by its own cell and number, so the episodes are the same).
    """
    root = Path(assets) if assets is not None else assets_root()
    catalog = load_catalog(root)
    if not catalog:
        raise TaskError(f"{root}: no catalog.json with objects")
    if count is not None and count < 1:
        raise TaskError(f"the number of episodes must be >= 1, got {count}")
    if split is None and metadata is None:
        raise TaskError("split None (every split) only selects from a metadata file; name a split to generate")
    wanted = split_types(split) if split is not None else None
    known = sorted({entry["category"] for entry in catalog})
    for category in categories or ():
        if category_slug(category) not in known:
            raise TaskError(f"unknown category '{category}'; the catalog has {', '.join(known)}")
    chosen_categories = {category_slug(c) for c in categories} if categories else None
    if types and wanted is not None:
        allowed = sorted({t for ts in wanted.values() for t in ts})
        bad = [t for t in types if t not in allowed]
        if bad:
            raise TaskError(f"task type {bad[0]} is not in split {split} (types {allowed[0]}-{allowed[-1]})")

    def keep(episode: Episode) -> bool:
        return ((wanted is None or episode.task_type in wanted.get(episode.split, ()))
                and (not types or episode.task_type in types)
                and (chosen_categories is None or category_slug(episode.obj_class) in chosen_categories))

    if metadata is not None:
        episodes = read_metadata(metadata)
        try:
            validate_episodes(episodes, catalog)
        except TaskError as err:
            raise TaskError(f"{metadata}: {err}") from None
        episodes = [e for e in episodes if keep(e)]
        if not episodes:
            raise TaskError(f"{metadata}: no episodes of split {split}" + (f", types {types}" if types else "")
                            + (f", categories {categories}" if categories else ""))
    else:
        chosen, all_cells = 0, {}
        for name, its_types in wanted.items():
            members = {e["category"] for e in catalog if name in e["splits"]}
            all_cells[name] = len(members) * len(SPLIT_TYPES[name])
            members &= chosen_categories if chosen_categories is not None else members
            chosen += len(members) * len([t for t in its_types if not types or t in types])
        if chosen == 0:
            raise TaskError(f"split {split} has no objects of categories {categories}")
        per_type = math.ceil(count / chosen) if count is not None else 1

        cells = frozenset((entry["category"], type_id) for entry in catalog for its_types in wanted.values()
                          for type_id in its_types if (not types or type_id in types)
                          and (chosen_categories is None or category_slug(entry["category"]) in chosen_categories))
        generated = _generated(catalog, root, seed, per_type, tuple(wanted), cells, pool)
        episodes = [e for e in _renumbered(generated, per_type, all_cells) if keep(e)]
    ordered = interleave(episodes)
    return ordered if count is None else ordered[:count]


def _generated(catalog: list[dict], root: Path, seed: int, per_type: int, splits: tuple[str, ...],
               cells: frozenset[tuple[str, int]], pool: Executor | None) -> list[Episode]:
    """`generate_episodes` of the (category, type) `cells`; with a process `pool`, one category per job."""
    if pool is None:
        return generate_episodes(catalog, root, seed, per_type, splits, cells=partial(_in_cells, cells))
    categories = sorted({category for category, _ in cells})
    jobs = [frozenset(cell for cell in cells if cell[0] == category) for category in categories]
    drawn = pool.map(partial(_generated, catalog, root, seed, per_type, splits, pool=None), jobs)
    return sorted((episode for episodes in drawn for episode in episodes), key=lambda episode: episode.ep_id)


def _in_cells(cells: frozenset[tuple[str, int]], category: str, type_id: int) -> bool:
    return (category, type_id) in cells


DRAW_IN_PROCESSES = 500
"""A selection of at least this many episodes is drawn in one process per core (drawing takes about 0.1 s an
episode on a core, mostly the grasp checks, and 0.3-5 s one with a turn in the air, `slot_rules.air_turn_fits`;
each process's start costs seconds)."""


def remembered_selection(out_dir: str | os.PathLike, split: str, count: int, seed: int = 0,
                         types: list[int] | None = None, categories: list[str] | None = None,
                         assets: str | os.PathLike | None = None) -> list[Episode]:
    """`select_episodes` without a metadata file, generated once per run directory: the episodes are kept in
    `out_dir/selections/<digest of the arguments>.json` (metadata schema) and read back when the same selection is
    asked for again, so a resumed run neither waits for the generator (minutes for thousands of episodes: the grasp
    checks) nor sees other episodes if the generator's code changed in between. DRAW_IN_PROCESSES or more episodes
    are drawn in one process per core."""
    selection = {"split": split, "count": count, "seed": seed, "types": sorted(types) if types else None,
                 "categories": sorted(category_slug(c) for c in categories) if categories else None,
                 "assets": str(Path(assets).resolve()) if assets is not None else None}
    digest = hashlib.sha256(json.dumps(selection, sort_keys=True).encode()).hexdigest()[:16]
    path = Path(out_dir) / SELECTIONS_DIR / f"{digest}.json"
    if path.exists():
        return interleave(read_metadata(path))
    with process_pool((os.cpu_count() or 1) if count >= DRAW_IN_PROCESSES else 1) as pool:
        episodes = select_episodes(split, count, seed, types, categories, None, assets, pool)
    write_metadata(episodes, path)
    return episodes


def _renumbered(episodes: list[Episode], per_type: int, cells: dict[str, int]) -> list[Episode]:
    """Episodes of `generate_episodes` with ep_ids numbered draw-first: split base + draw x cells + cell, where a cell
    is a (category, type) of the split and `cells` counts them per split. generate_episodes numbers cell-first, so
    its ids change with per_type; these do not, so a run asked for more episodes later keeps the ids (and the
    resume) of the smaller one."""
    out = []
    for e in episodes:
        base = SPLITS.index(e.split) * SPLIT_ID_STRIDE
        cell, draw = divmod(e.ep_id - base, per_type)
        out.append(replace(e, ep_id=base + draw * cells[e.split] + cell))
    return sorted(out, key=lambda e: e.ep_id)


def interleave(episodes: list[Episode]) -> list[Episode]:
    """Round-robin over task types; within a type, by draw index and then categories rotated by the type's rank, so
    a prefix spreads over types first and over categories second."""
    by_type: dict[int, list[Episode]] = {}
    for episode in sorted(episodes, key=lambda e: e.ep_id):
        by_type.setdefault(episode.task_type, []).append(episode)
    queues = []
    for rank, type_id in enumerate(sorted(by_type)):
        mine = by_type[type_id]
        categories = sorted({category_slug(e.obj_class) for e in mine})
        draw: dict[tuple[str, str], int] = {}
        keyed = []
        for episode in mine:
            cell = (episode.split, category_slug(episode.obj_class))
            draw[cell] = draw.get(cell, -1) + 1
            keyed.append(((draw[cell], (categories.index(cell[1]) - rank) % len(categories), episode.ep_id), episode))
        queues.append([episode for _, episode in sorted(keyed, key=lambda item: item[0])])
    ordered = []
    for i in range(max((len(q) for q in queues), default=0)):
        ordered += [q[i] for q in queues if i < len(q)]
    return ordered
