"""Re-simulate stored demonstrations: reset a fresh env to each demo's episode, step its actions, check success.

A demo reproduces when the task (task mode, as it was recorded) succeeds within its stored number of steps. The
reset state is compared with the demo's stored initial_state, and optionally a second env in skill mode checks
that the same actions also complete the skill chain.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import jax
import numpy as np

from partinstruct_mjx.errors import DataError

_LEDGER = "progress.json"


@dataclass(frozen=True)
class ReplayResult:
    ep_id: int
    obj_id: str
    task_type: int
    steps: int
    """Stored length of the demo."""
    task_success_step: int | None
    """Steps until task success in the replay (None: not within the stored length)."""
    skill_success_step: int | None
    """Steps until the skill chain completed in skill mode (None: not within the length, or not checked)."""
    reset_error: float | None
    """Largest absolute difference between the replay's reset physics state and the stored one (None: no state)."""

    @property
    def reproduced(self) -> bool:
        return self.task_success_step is not None


def load_stored_demos(path: str | os.PathLike, limit: int | None = None) -> list[dict]:
    """The successful demos of a run directory, or of one HDF5 file inside it (data/<category>.hdf5 or a shard),
    in ep_id order: dicts with 'episode', 'actions' and 'initial_state'. DataError if there are none."""
    from partinstruct_mjx.data.demos import _episode, load_sidecar

    path = Path(path)
    run_dir = path if path.is_dir() else next((p for p in path.parents if (p / _LEDGER).exists()), None)
    if run_dir is None or not (run_dir / _LEDGER).exists():
        raise DataError(f"{path}: not a demonstration run directory (no {_LEDGER}) or a file inside one")
    ledger = json.loads((run_dir / _LEDGER).read_text())
    if path.is_dir():
        wanted = sorted(int(ep_id) for ep_id, shard in ledger["episodes"].items() if shard)
    else:
        try:
            with h5py.File(path, "r") as file:
                wanted = sorted(int(demo.attrs["ep_id"]) for demo in file["data"].values())
        except (OSError, KeyError) as err:
            raise DataError(f"{path}: not a demonstration HDF5 file ({err})") from None
    demos = []
    for ep_id in wanted[:limit]:
        record = load_sidecar(run_dir, ep_id)
        if not record["success"] or not record["shard"]:
            continue
        with h5py.File(run_dir / record["shard"], "r") as file:
            actions = file["data"][record["demo"]]["actions"][()]
        demos.append({"episode": _episode(record), "actions": actions,
                      "initial_state": np.asarray(record["initial_state"], float)})
    if not demos:
        raise DataError(f"{path}: no successful demos to replay")
    return demos


def replay_demos(path: str | os.PathLike, batch_size: int = 16, skill_mode: bool = False, limit: int | None = None,
                 backend: str = "mujoco", assets: str | os.PathLike | None = None,
                 num_threads: int | None = None) -> list[ReplayResult]:
    """Replay the stored demos of `path` (see load_stored_demos), demos of one object batched together."""
    from partinstruct_mjx.data.synthesis import object_batches, object_groups, object_paths
    from partinstruct_mjx.paths import assets_root

    demos = load_stored_demos(path, limit)
    root = Path(assets) if assets is not None else assets_root()
    objects = object_paths([d["episode"] for d in demos], root)
    results = []
    for key, mine in object_groups(demos, episode_of=lambda demo: demo["episode"]).items():
        for batch, size in object_batches(mine, batch_size):
            results += _replay_batch(objects[key], batch, size, skill_mode, backend, num_threads)
    return sorted(results, key=lambda r: r.ep_id)


def _replay_batch(object_xml: Path, batch: list[dict], size: int, skill_mode: bool, backend: str,
                  num_threads: int | None) -> list[ReplayResult]:
    from partinstruct_mjx.env import EnvConfig, PartInstructEnv

    padded = [batch[i % len(batch)] for i in range(size)]
    episodes = [d["episode"] for d in padded]
    lengths = np.array([len(d["actions"]) for d in padded])
    horizon = int(lengths.max())
    actions = np.stack([np.concatenate([d["actions"], np.repeat(d["actions"][-1:], horizon - len(d["actions"]), 0)])
                        for d in padded]).astype(np.float32)
    modes = [False, True] if skill_mode else [False]
    envs = [PartInstructEnv(object_xml, size, EnvConfig(backend=backend, skill_mode=mode, num_threads=num_threads))
            for mode in modes]
    try:
        key = jax.random.PRNGKey(0)
        states = [env.reset(key, episodes) for env in envs]
        reset_error = [None] * size
        if hasattr(envs[0].backend, "get_physics_state"):
            physics = envs[0].backend.get_physics_state()
            reset_error = [float(np.abs(physics[b] - d["initial_state"]).max())
                           if d["initial_state"].shape == physics[b].shape else float("inf")
                           for b, d in enumerate(padded)]
        first_success = [np.zeros(size, int) for _ in envs]
        for t in range(horizon):
            for i, env in enumerate(envs):
                states[i] = env.step(states[i], actions[:, t])
                success = np.asarray(states[i].task.success) & (first_success[i] == 0) & (t < lengths)
                first_success[i][success] = t + 1
            if all((f > 0).all() for f in first_success):
                break
    finally:
        for env in envs:
            env.close()
    return [ReplayResult(d["episode"].ep_id, d["episode"].obj_id, d["episode"].task_type, int(lengths[b]),
                         int(first_success[0][b]) or None,
                         (int(first_success[1][b]) or None) if skill_mode else None, reset_error[b])
            for b, d in enumerate(batch)]


def replay_table(results: list[ReplayResult], skill_mode: bool = False) -> str:
    """One line per demo and a total line; the skill-success column only if skill mode was checked."""
    lines = [f"{'ep_id':>8}  {'object':<14} {'type':>4} {'steps':>5}  {'task success':>12}  {'skill success':>13}  "
             f"{'reset error':>11}"]
    for r in results:
        task = f"step {r.task_success_step}" if r.task_success_step else "NO"
        skill = "-" if not skill_mode else f"step {r.skill_success_step}" if r.skill_success_step else "NO"
        error = "-" if r.reset_error is None else f"{r.reset_error:.1e}"
        lines.append(f"{r.ep_id:>8}  {r.obj_id:<14} {r.task_type:>4} {r.steps:>5}  {task:>12}  {skill:>13}  "
                     f"{error:>11}")
    ok = sum(r.reproduced for r in results)
    lines.append(f"{ok}/{len(results)} demos reach task success within their stored length")
    if skill_mode:
        lines.append(f"{sum(r.skill_success_step is not None for r in results)}/{len(results)} complete the skill "
                     f"chain in skill mode")
    return "\n".join(lines)
