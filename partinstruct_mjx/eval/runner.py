"""The evaluation runner: episodes per split, batched rollouts per object, per-episode records, results files.

Episodes come from `select_episodes` (seeded generation, or a metadata file) per split; they are run grouped by
object (one env per object and batch size, as in demo synthesis) until every scene's episode has ended: at success
or at its horizon (250 env steps, 400 for test4, or `max_steps`). A scene whose episode ended keeps being stepped
while others run, but its outcome is frozen at its end. After every batch results.json is rewritten atomically,
so an interrupted run loses no finished batch and the same command resumes it.
"""

from __future__ import annotations

import json
import os
import threading
import time
import warnings
from collections.abc import Iterator
from concurrent.futures import Executor
from dataclasses import asdict, replace
from pathlib import Path

import jax
import numpy as np

from partinstruct_mjx.assets.partnet import category_slug
from partinstruct_mjx.atomic import atomic_write
from partinstruct_mjx.eval.config import EvalConfig, EvalError
from partinstruct_mjx.eval.metrics import aggregate, results_markdown
from partinstruct_mjx.eval.planner import Planner, make_planner
from partinstruct_mjx.eval.policy import OraclePolicy, Policy, load_policy
from partinstruct_mjx.eval.skills import SkillProgress
from partinstruct_mjx.tasks.episodes import SPLITS, Episode, write_metadata
from partinstruct_mjx.workers import default_workers, process_pool, run_in_threads, threads_per_worker

RESULTS = "results.json"
REPORT = "results.md"
EPISODES = "episodes.json"
"""The run's episodes in the metadata schema: `--metadata DIR/episodes.json` evaluates the same ones elsewhere."""
SCHEMA_VERSION = 1


def select_eval_episodes(config: EvalConfig, pool: Executor | None = None) -> list[Episode]:
    """Each split's episodes (in `select_episodes`' order, which spreads a prefix over task types and categories),
    splits in config order; with a process `pool`, each category's episodes are drawn in one of its processes."""
    from partinstruct_mjx.data.synthesis import select_episodes

    episodes = []
    for split in config.splits:
        episodes += select_episodes(split, config.episodes_per_split, config.seed, None,
                                    list(config.categories) if config.categories else None, config.metadata,
                                    config.assets, pool)
    return episodes


def evaluate(config: EvalConfig, out_dir: str | os.PathLike, policy: Policy | None = None,
             planner: Planner | None = None, progress: bool = True) -> dict:
    """Evaluate a policy on `config`'s splits and write results.json, results.md and videos to `out_dir`.

    `policy` / `planner` objects replace the ones `config.policy` / `config.planner` name (which then only label
    the run). Episodes already in `out_dir`'s results.json (same settings) are kept, not run again; EvalError if
    `out_dir` holds a run with other settings. Returns the results dict written to results.json.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise EvalError(f"--out {out_dir} is a file, not a directory")
    given_policy, given_planner = policy is not None, planner is not None
    if config.processes > 1 and (given_policy or given_planner):
        raise EvalError(f"--processes {config.processes}: each process loads the policy and planner its config names; "
                        f"evaluate() was handed {'a policy' if given_policy else 'a planner'} object: use processes=1")
    # The pool's settings hold from here: the policy loaded here (to check it) does not take the GPU's memory from
    # the processes (JAX preallocates 75 % of it by default: with 16 processes, a trained policy ran out of memory).
    with process_pool(config.processes) as pool:
        if policy is None:
            policy = load_policy(config.policy, config.oracle_tries)
        if not isinstance(policy, Policy):
            raise EvalError(f"the policy ({type(policy).__name__}) lacks reset(env, state, key) / act(env, state, "
                            f"instructions, key)")
        if planner is None:
            planner = make_planner(config.planner)
        elif not isinstance(planner, Planner):
            raise EvalError(f"the planner ({type(planner).__name__}) lacks instructions(env, state, step)")
        if config.videos:
            _check_opengl()
        return _evaluate(config, out_dir, policy, planner, pool, progress)


def _evaluate(config: EvalConfig, out_dir: Path, policy: Policy, planner: Planner | None, pool: Executor | None,
              progress: bool) -> dict:
    """`evaluate` once its policy and planner are set: objects rolled out in worker threads, or in `pool`'s
    processes."""
    from tqdm import tqdm

    from partinstruct_mjx.data.synthesis import object_groups, object_paths
    from partinstruct_mjx.paths import assets_root
    from partinstruct_mjx.provenance import provenance

    finished = _finished(out_dir, config)
    episodes, read_back = _run_episodes(config, out_dir, pool, resuming=(out_dir / RESULTS).exists())
    objects = object_paths(episodes, Path(config.assets) if config.assets else assets_root())
    wanted = {e.ep_id for e in episodes}
    records = {ep_id: r for ep_id, r in finished.items() if ep_id in wanted}
    filmed = set()
    for split in config.splits:
        filmed.update(e.ep_id for e in [e for e in episodes if e.split == split][:config.videos])
    todo = [e for e in episodes if e.ep_id not in records]
    meta = {"label": _label(config), "resolved": _resolved(config, episodes, policy, planner),
            "run": {"resumed_episodes": len(records), "episodes_run": 0, "wall_s": 0.0}, "provenance": provenance(),
            "unwritten_episodes": None if read_back else episodes}

    start = time.perf_counter()
    groups = _largest_first(object_groups(todo))
    workers = config.processes if pool is not None else max(1, min(_workers(config, policy, planner), len(groups)))
    threads_each = threads_per_worker(config.num_threads, workers)
    meta["run"].update(workers=workers, processes=config.processes)
    # Each worker thread acts with a policy (and planner) of its own: they keep per-batch state.
    agents = [(policy, planner)] + [(policy.fork(), None if planner is None else planner.fork())
                                    for _ in range(workers - 1 if pool is None else 0)]
    lock = threading.Lock()
    bar = tqdm(total=len(todo), desc="eval", unit="episode", disable=not progress or not todo)

    def run_object(slot: int, group, stop: threading.Event) -> None:
        """Roll out one object's batches (until the run stops), here or in a worker process; record and write
        what each returns."""
        obj, mine = group
        if pool is None:
            finished_batches = _object_records(objects[obj], mine, *agents[slot], config, threads_each, filmed,
                                               out_dir, stop)
        else:
            finished_batches = _in_process(pool, stop, _process_object_records, objects[obj], mine, config,
                                           threads_each, filmed, out_dir)
        for finished in finished_batches:
            with lock:
                records.update((record["ep_id"], record) for record in finished)
                meta["run"]["episodes_run"] += len(finished)
                meta["run"]["wall_s"] = time.perf_counter() - start
                _write(out_dir, config, meta, records, complete=False)
                successes = sum(r["success"] for r in records.values())
                bar.set_postfix(
                    episodes_per_min=f"{60 * meta['run']['episodes_run'] / meta['run']['wall_s']:.1f}",
                    success=f"{successes / len(records):.0%}", refresh=False)
                bar.update(len(finished))

    try:
        run_in_threads(groups, workers, run_object, "partinstruct-eval")
    finally:
        bar.close()
        for agent, _ in agents:
            if isinstance(agent, OraclePolicy):
                agent.close()
    meta["run"]["wall_s"] = time.perf_counter() - start
    return _write(out_dir, config, meta, records, complete=True)


def _run_episodes(config: EvalConfig, out_dir: Path, pool: Executor | None,
                  resuming: bool) -> tuple[list[Episode], bool]:
    """The run's episodes, and whether they came from `out_dir`/EPISODES: a resumed run that drew them reads them
    back from there (so a resume neither waits for the draw again nor depends on it giving the same episodes on
    another machine or after a code change), and so does a run whose --metadata is that file; else they are drawn
    or read from --metadata, and `_write` keeps them in EPISODES with the first results."""
    path = out_dir / EPISODES
    if config.metadata is not None:
        return select_eval_episodes(config, pool), path.exists() and path.samefile(config.metadata)
    if resuming and path.exists():
        return select_eval_episodes(replace(config, metadata=str(path))), True
    return select_eval_episodes(config, pool), False


def _largest_first(groups: dict[tuple[str, str], list[Episode]]) -> list[tuple[tuple[str, str], list[Episode]]]:
    """The object groups, the most env steps to run first (by their episodes' step limits), so that the workers
    finish together."""
    from partinstruct_mjx.env import step_limit

    return sorted(groups.items(), key=lambda group: -sum(step_limit(e.split) for e in group[1]))


def _object_records(object_xml: Path, episodes: list[Episode], policy: Policy, planner: Planner | None,
                    config: EvalConfig, num_threads: int, filmed: set[int], out_dir: Path,
                    stop: threading.Event | None = None) -> Iterator[list[dict]]:
    """Roll out one object's episodes batch by batch (one env per batch size) until `stop` is set; yield each
    batch's records."""
    from partinstruct_mjx.data.synthesis import object_batches

    key = jax.random.PRNGKey(config.seed)
    envs = {}
    try:
        for batch, size in object_batches(episodes, config.batch_size):
            if stop is not None and stop.is_set():
                return
            if size not in envs:
                envs[size] = _make_env(object_xml, size, config, num_threads)
            yield _run_batch(envs[size], batch, policy, planner, config, key, filmed, out_dir)
    finally:
        for env in envs.values():
            env.close()


_PROCESS_AGENTS: dict[EvalConfig, tuple[Policy, Planner | None]] = {}
"""A worker process's policy and planner, loaded once from the config they serve."""


def _process_object_records(object_xml: Path, episodes: list[Episode], config: EvalConfig, num_threads: int,
                            filmed: set[int], out_dir: Path) -> list[dict]:
    """A worker process's job: one object's episodes with the process's own policy and planner; their records."""
    if config not in _PROCESS_AGENTS:
        _PROCESS_AGENTS[config] = load_policy(config.policy, config.oracle_tries), make_planner(config.planner)
    agents = _PROCESS_AGENTS[config]
    return [record for finished in _object_records(object_xml, episodes, *agents, config, num_threads, filmed,
                                                   out_dir) for record in finished]


def _in_process(pool: Executor, stop: threading.Event, function, *args) -> list:
    """[function(*args)] run in `pool`; [] if `stop` is set first (the job is then cancelled if it has not
    started)."""
    future = pool.submit(function, *args)
    while True:
        try:
            return [future.result(timeout=1.0)]
        except TimeoutError:
            if stop.is_set():
                future.cancel()
                return []


def _workers(config: EvalConfig, policy: Policy, planner: Planner | None) -> int:
    """Worker threads: `config.workers`, by default `default_workers` where the policy and planner can fork (one
    copy per thread), else 1. EvalError for several workers asked of a policy or planner that cannot fork."""
    unforkable = [a for a in (policy, planner) if a is not None and not callable(getattr(a, "fork", None))]
    if config.workers is None:
        return 1 if unforkable else default_workers(config.backend)
    if config.workers > 1 and unforkable:
        raise EvalError(f"--workers {config.workers} needs a policy and planner with fork() (a copy for each worker "
                        f"thread); {type(unforkable[0]).__name__} has none: use --workers 1")
    return config.workers


def _make_env(object_xml: Path, size: int, config: EvalConfig, num_threads: int):
    from partinstruct_mjx.env import EnvConfig, PartInstructEnv

    return PartInstructEnv(object_xml, size, EnvConfig(backend=config.backend, skill_mode=config.mode == "skill",
                                                       num_threads=num_threads))


def _run_batch(env, batch: list[Episode], policy: Policy, planner: Planner | None, config: EvalConfig,
               key: jax.Array, filmed: set[int], out_dir: Path) -> list[dict]:
    """Roll out one batch (padded to the env's size) until every scene's episode ended; one record per episode."""
    from partinstruct_mjx.data.synthesis import pad_batch

    size, real = env.batch_size, len(batch)
    state = env.reset(key, pad_batch(batch, size))
    skills = SkillProgress(env)
    skills.reset(state)
    policy.reset(env, state, key)
    act_key = jax.random.fold_in(key, batch[0].ep_id)
    horizon = np.asarray(state.info["step_limit"])
    if config.max_steps is not None:
        horizon = np.minimum(horizon, config.max_steps)
    ended = np.arange(size) >= real  # the rows that pad the batch are not simulated
    success, unstable, completion = np.zeros(size, bool), np.zeros(size, bool), np.zeros(size)
    steps, skill_at = np.zeros(size, int), np.zeros(size, int)
    films = {b: _Film(batch[b], b, state, skills.index(state)[b]) for b in range(real) if batch[b].ep_id in filmed}
    instructions = None
    for t in range(int(horizon.max())):
        if planner is None:
            instructions = env.instructions(state)
        elif t % config.planner_every == 0:
            instructions = planner.instructions(env, state, t)
            if len(instructions) != size or not all(isinstance(i, str) for i in instructions):
                raise EvalError(f"the planner must return {size} strings (one per scene), got {instructions!r}")
        action = policy.act(env, state, instructions, jax.random.fold_in(act_key, t))
        state = env.step(state, action, ~ended)
        skills.update(state)
        now = ~ended & (np.asarray(state.done) | (t + 1 >= horizon))
        index = skills.index(state)
        for b, film in films.items():
            if not ended[b]:
                film.add(state, index[b])
        if now.any():
            success[now] = np.asarray(state.task.success)[now]
            unstable[now] = np.asarray(state.info["unstable"])[now]
            completion[now] = np.asarray(state.task.completion)[now]
            steps[now], skill_at[now] = t + 1, index[now]
            ended |= now
        if ended.all():
            break
    records = [_record(batch[b], bool(success[b]), float(completion[b]), int(steps[b]), int(horizon[b]),
                       int(skill_at[b]), bool(unstable[b])) for b in range(real)]
    for b, film in films.items():
        with _RENDER_LOCK:
            records[b]["video"] = film.render(env, out_dir, records[b])
    return records


_RENDER_LOCK = threading.Lock()
"""Videos are rendered one at a time (one OpenGL context in use, one ffmpeg encoder running)."""


class _Film:
    """qpos and the current skill's target part of one scene, step by step, for its video."""

    def __init__(self, episode: Episode, row: int, state, skill: int):
        self.episode, self.row = episode, row
        self.qpos, self.part = [], []
        self.add(state, skill)

    def add(self, state, skill: int) -> None:
        from partinstruct_mjx.obs.video import NO_PART

        chain = self.episode.chain
        part = chain[skill].part if skill < len(chain) else None
        self.qpos.append(np.array(state.data.qpos[self.row]))  # a copy: the mujoco backend reuses its buffers
        self.part.append(NO_PART if part is None else part)

    def render(self, env, out_dir: Path, record: dict) -> str:
        from partinstruct_mjx.obs.video import Trajectory, render_video

        e = self.episode
        name = (f"videos/{e.split}/{e.ep_id}_{category_slug(e.obj_class)}_{e.obj_id}_type{e.task_type}_"
                f"{'success' if record['success'] else 'failure'}.mp4")
        with warnings.catch_warnings():  # ffmpeg is fork+exec'd, which JAX's fork warning does not concern
            warnings.filterwarnings("ignore", r"os\.fork\(\) was called", RuntimeWarning)
            render_video(Trajectory(np.stack(self.qpos), Path(env.scene.object_xml), tuple(self.part),
                                    f"episode {e.ep_id}"), out_dir / name)
        return name


def _record(episode: Episode, success: bool, completion: float, steps: int, horizon: int, skill_at: int,
            unstable: bool) -> dict:
    """One episode's outcome: what results.json stores per episode. `physics_unstable`: the episode ended early,
    without success, because its simulation diverged (NaN or huge joint values)."""
    chain = episode.chain
    skill_at = min(skill_at, len(chain))
    return {"split": episode.split, "category": category_slug(episode.obj_class), "obj_id": episode.obj_id,
            "ep_id": episode.ep_id, "task_type": episode.task_type, "success": success,
            "completion": round(completion, 6), "steps": steps, "step_limit": horizon, "physics_unstable": unstable,
            "stopped_skill": chain[skill_at].name if skill_at < len(chain) else None,
            "skills": [step.name for step in chain], "skill_success": [i < skill_at for i in range(len(chain))],
            "target_parts": [step.part for step in chain if step.part is not None],
            "task_instruction": episode.task_instruction, "video": None}


def _label(config: EvalConfig) -> str:
    """The table's row label: policy (a run directory's name), planner, mode."""
    name = Path(config.policy).name or config.policy
    planner = f" + {config.planner} planner" if config.planner else ""
    return f"{name}{planner} ({config.mode} mode)"


def _resolved(config: EvalConfig, episodes: list[Episode], policy: Policy, planner: Planner | None) -> dict:
    from partinstruct_mjx.env import step_limit

    limits = {s: step_limit(s) for s in config.splits}
    return {"config": asdict(config), "policy_class": type(policy).__qualname__,
            "planner_class": None if planner is None else type(planner).__qualname__,
            "episodes_per_split": {s: sum(e.split == s for e in episodes) for s in config.splits},
            "step_limits": {s: min(n, config.max_steps or n) for s, n in limits.items()},
            "env": {"backend": config.backend, "skill_mode": config.mode == "skill", "rotation": "euler",
                    "control_hz": 20}}


def _finished(out_dir: Path, config: EvalConfig) -> dict[int, dict]:
    """Records of a previous run in `out_dir` with the same settings; EvalError if its settings differ."""
    path = out_dir / RESULTS
    if not path.exists():
        return {}
    try:
        previous = json.loads(path.read_text())
        identity, episodes = previous["identity"], previous["episodes"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise EvalError(f"{path}: not an evaluation results file ({err}); use another --out") from None
    mine = config.identity()
    changed = sorted(k for k in set(mine) | set(identity) if mine.get(k) != identity.get(k))
    if changed:
        differences = "; ".join(f"{k}: {identity.get(k)!r} there, {mine.get(k)!r} now" for k in changed)
        raise EvalError(f"{out_dir} holds an evaluation with other settings ({differences}); use another --out "
                        f"to start a new one or the same settings to resume it")
    return {r["ep_id"]: r for r in episodes}


def _write(out_dir: Path, config: EvalConfig, meta: dict, records: dict[int, dict], complete: bool) -> dict:
    ordered = sorted(records.values(), key=lambda r: (SPLITS.index(r["split"]), r["ep_id"]))
    results = {"schema_version": SCHEMA_VERSION, "complete": complete, "label": meta["label"],
               "config": meta["resolved"]["config"], "identity": config.identity(), "resolved": meta["resolved"],
               "run": meta["run"], "provenance": meta["provenance"],
               "summary": aggregate(ordered, list(config.splits)), "episodes": ordered}
    if meta["unwritten_episodes"] is not None:
        write_metadata(meta["unwritten_episodes"], out_dir / EPISODES)
        meta["unwritten_episodes"] = None
    with atomic_write(out_dir / RESULTS) as file:
        json.dump(results, file, indent=1)
        file.write("\n")
    if complete:
        with atomic_write(out_dir / REPORT) as file:
            file.write(results_markdown(results))
    return results


def _check_opengl() -> None:
    """Fail before any rollout when videos are asked for but no OpenGL context can be made."""
    import mujoco

    try:
        context = mujoco.GLContext(16, 16)
        context.make_current()
        context.free()
    except Exception as err:  # noqa: BLE001 (every backend raises its own type)
        raise EvalError(f"--videos needs OpenGL, which failed ({err}); headless, set MUJOCO_GL=egl") from None
