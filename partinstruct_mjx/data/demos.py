"""Demonstrations on disk: a resumable writer of shards and per-episode sidecars, merged into robomimic files.

Layout of a run directory:
    progress.json                     the ledger: env_args, observation layout, committed ep_id -> shard (or null)
    shards/<category>/<ep>-<n>.hdf5   one per category and `add` call: n demos, the lowest ep_id <ep>
    episodes/<ep_id>.json             sidecar: the episode, success, failing skill, steps, skill boundaries, state
    data/<category>.hdf5              written by finalize: robomimic layout, data/demo_0 ... in ep_id order
    metadata.json, summary.json       written by finalize: metadata of the successes; counts and provenance

Commit protocol of `add`: shards, then sidecars (each atomically), then the ledger; rewriting the ledger is the
commit. An interrupted batch is therefore absent from the ledger, and its files are removed when the directory is
next opened. Shards are kept: finalize re-merges them (it is idempotent and re-runnable after more adds).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from partinstruct_mjx.assets.partnet import category_slug
from partinstruct_mjx.assets.procedural.categories import CATEGORIES
from partinstruct_mjx.atomic import atomic_path, atomic_write
from partinstruct_mjx.errors import DataError
from partinstruct_mjx.provenance import provenance
from partinstruct_mjx.tasks.episodes import Episode, write_metadata
from partinstruct_mjx.tasks.skills import SkillStep

ACTION_SIZE = 7
"""Absolute [x, y, z, roll, pitch, yaw, finger]."""
CHUNK_STEPS = 16
"""Steps per HDF5 chunk of a per-step array of arrays. With the byte shuffle, 16-step chunks of real clouds take 31 %
less space than lzf alone per step and write 20 % faster (a sequence reader of 16 steps touches one or two chunks)."""

_LEDGER = "progress.json"
_OBS_KEY = re.compile(r"^[A-Za-z0-9_]+$")


@dataclass(frozen=True)
class Demo:
    """One successful episode: T actions, T observations per key, the executing skill per step, the reset state.

    Arrays are converted on construction (actions float32, skill_index int32, initial_state float64); malformed
    input raises DataError naming the episode and the field.
    """

    episode: Episode
    actions: np.ndarray
    """(T, 7) absolute [x, y, z, roll, pitch, yaw, finger]."""
    obs: dict[str, np.ndarray]
    """Each (T, ...), e.g. agentview_pcd (T, 1024, 3), tcp_pose (T, 7)."""
    skill_index: np.ndarray
    """(T,) index into episode.chain of the skill executed at each step; non-decreasing."""
    initial_state: np.ndarray
    """(nstate,) MuJoCo physics state right after reset, for exact re-simulation."""

    def __post_init__(self):
        name = f"episode {self.episode.ep_id}"
        actions = np.asarray(self.actions, dtype=np.float32)
        if actions.ndim != 2 or actions.shape[1] != ACTION_SIZE or len(actions) == 0:
            raise DataError(f"{name}: actions have shape {actions.shape}; expected (T, {ACTION_SIZE}) with T >= 1")
        if not np.isfinite(actions).all():
            raise DataError(f"{name}: actions contain NaN or infinity")
        steps = len(actions)
        if not isinstance(self.obs, dict) or not self.obs:
            raise DataError(f"{name}: obs must be a non-empty dict of arrays")
        obs = {}
        for key, value in self.obs.items():
            value = np.asarray(value)
            if not isinstance(key, str) or not _OBS_KEY.match(key):
                raise DataError(f"{name}: obs key {key!r} is not a plain name (letters, digits, '_')")
            if value.ndim == 0 or len(value) != steps or not (np.issubdtype(value.dtype, np.number)
                                                               or value.dtype == bool):
                raise DataError(f"{name}: obs['{key}'] has shape {value.shape} and dtype {value.dtype}; "
                                f"expected numbers with {steps} steps like the actions")
            obs[key] = value
        skills = np.asarray(self.skill_index)
        if skills.shape != (steps,) or not np.issubdtype(skills.dtype, np.integer):
            raise DataError(f"{name}: skill_index has shape {skills.shape} and dtype {skills.dtype}; "
                            f"expected ({steps},) integers")
        if skills.min() < 0 or skills.max() >= len(self.episode.chain) or (np.diff(skills) < 0).any():
            raise DataError(f"{name}: skill_index must be non-decreasing in [0, {len(self.episode.chain)}) "
                            f"(the chain's skills in order), got {np.unique(skills).tolist()}")
        state = np.asarray(self.initial_state, dtype=np.float64)
        if state.ndim != 1 or len(state) == 0 or not np.isfinite(state).all():
            raise DataError(f"{name}: initial_state must be a finite non-empty vector, got shape {state.shape}")
        for field, value in (("actions", actions), ("obs", obs), ("skill_index", skills.astype(np.int32)),
                             ("initial_state", state)):
            object.__setattr__(self, field, value)

    @property
    def steps(self) -> int:
        return len(self.actions)

    @property
    def skill_boundaries(self) -> list[int]:
        """First step of each chain skill (a skill that took no steps starts where the next one does)."""
        return np.searchsorted(self.skill_index, np.arange(len(self.episode.chain))).tolist()


def read_ledger(out_dir: str | os.PathLike) -> dict | None:
    """A run directory's ledger, or None before its first run."""
    path = Path(out_dir) / _LEDGER
    return json.loads(path.read_text()) if path.exists() else None


def demo_files(data_dir: str | os.PathLike) -> list[Path]:
    """The robomimic files of a `partinstruct demos` run directory; DataError naming what is missing."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise DataError(f"{data_dir}: no such data directory (expected the --out directory of `partinstruct demos`)")
    files = sorted((data_dir / "data").glob("*.hdf5"))
    if not files:
        raise DataError(f"{data_dir}: no demonstration files data/*.hdf5, not a demos run directory; run "
                        f"`partinstruct demos --out {data_dir}` first (it writes them when it finishes or is "
                        "interrupted)")
    return files


def check_env_args(out_dir: str | os.PathLike, env_args: dict) -> None:
    """Refuse (DataError) a run directory that was started with other env_args; a new directory passes."""
    ledger = read_ledger(out_dir)
    if ledger is not None and ledger["env_args"] != env_args:
        raise DataError(f"{out_dir} was started with env_args {ledger['env_args']}, not {env_args}; use a new "
                        f"directory for a different environment")


class DemoWriter:
    """Writes the demos and failures of one run directory; resumable (see the module docstring for the protocol).

    Opening removes the files of a batch whose commit was interrupted, and refuses a directory started with other
    env_args. Concurrent writers on one directory are serialised by a lock file.
    """

    def __init__(self, out_dir: str | os.PathLike, env_args: dict):
        self.out_dir = Path(out_dir)
        try:
            self.env_args = json.loads(json.dumps(env_args))
        except (TypeError, ValueError) as err:
            raise DataError(f"env_args must be a JSON-able dict: {err}") from None
        self.out_dir.mkdir(parents=True, exist_ok=True)
        with self._locked():
            check_env_args(self.out_dir, self.env_args)
            ledger = self._ledger()
            if ledger is None:
                self._write_ledger({"env_args": self.env_args, "obs_layout": None, "episodes": {}})
            else:
                self._remove_uncommitted(ledger)

    def finished_ids(self) -> set[int]:
        """ep_ids committed so far, successes and failures: a resumed run skips them."""
        return {int(ep_id) for ep_id in self._ledger()["episodes"]}

    def add(self, demos: list[Demo], failures: list[tuple[Episode, str]]) -> None:
        """Commit one batch: successful demos and (episode, failing skill or 'timeout') pairs, all or nothing.

        DataError, with nothing written, for an ep_id repeated or already committed, an unknown category, a failing
        skill that is not a name, or observations laid out unlike the run's earlier demos.
        """
        episodes = [demo.episode for demo in demos] + [episode for episode, _ in failures]
        repeated = sorted(ep_id for ep_id, n in Counter(e.ep_id for e in episodes).items() if n > 1)
        if repeated:
            raise DataError(f"episode {repeated[0]} appears more than once in the batch")
        for episode, skill in failures:
            if not isinstance(skill, str) or not skill:
                raise DataError(f"episode {episode.ep_id}: failing skill must be a name, got {skill!r}")
        categories = {episode.ep_id: _category(episode) for episode in episodes}
        if not episodes:
            return
        with self._locked():
            ledger = self._ledger()
            done = sorted(e.ep_id for e in episodes if str(e.ep_id) in ledger["episodes"])
            if done:
                raise DataError(f"episode {done[0]} is already committed in {self.out_dir}; skip finished_ids()")
            layout = ledger["obs_layout"]
            for demo in demos:
                layout = _check_layout(demo, layout)
            written: list[Path] = []
            try:
                shards = self._write_shards(demos, categories, written)
                records = [_sidecar(d.episode, d, shards[d.episode.ep_id], None) for d in demos]
                records += [_sidecar(episode, None, None, skill) for episode, skill in failures]
                for record in sorted(records, key=lambda r: r["ep_id"]):
                    path = self.out_dir / "episodes" / f"{record['ep_id']}.json"
                    with atomic_write(path) as file:
                        json.dump(record, file, indent=1)
                        file.write("\n")
                    written.append(path)
                for record in records:
                    ledger["episodes"][str(record["ep_id"])] = record["shard"]
                ledger["obs_layout"] = layout
                self._write_ledger(ledger)
            except BaseException:
                for path in written:
                    path.unlink(missing_ok=True)
                raise

    def _write_shards(self, demos: list[Demo], categories: dict[int, str], written: list[Path]) -> dict[int, str]:
        """One shard per category of `demos` (appended to `written`); returns ep_id -> shard path in out_dir."""
        shards = {}
        for category in sorted(set(categories[d.episode.ep_id] for d in demos)):
            mine = sorted((d for d in demos if categories[d.episode.ep_id] == category), key=lambda d: d.episode.ep_id)
            shard = f"shards/{category}/{mine[0].episode.ep_id}-{len(mine)}.hdf5"
            with atomic_path(self.out_dir / shard) as temporary, h5py.File(temporary, "w") as file:
                group = file.create_group("data")
                for demo in mine:
                    _write_demo(group.create_group(f"ep_{demo.episode.ep_id}"), demo)
                    shards[demo.episode.ep_id] = shard
            written.append(self.out_dir / shard)
        return shards

    def finalize(self) -> dict:
        """Merge the shards into data/<category>.hdf5, write metadata.json and summary.json; return the summary.

        Idempotent; run it again after more adds to include them.
        """
        with self._locked():
            ledger = self._ledger()
            records = [load_sidecar(self.out_dir, ep_id) for ep_id in sorted(map(int, ledger["episodes"]))]
            successes = [r for r in records if r["success"]]
            by_category: dict[str, list[dict]] = {}
            for record in successes:
                by_category.setdefault(category_slug(record["obj_class"]), []).append(record)
            for category, mine in sorted(by_category.items()):
                self._merge(category, mine)
            write_metadata([_episode(r) for r in successes], self.out_dir / "metadata.json")
            summary = _summary(records, by_category)
            with atomic_write(self.out_dir / "summary.json") as file:
                json.dump(summary, file, indent=1)
                file.write("\n")
            return summary

    def _merge(self, category: str, records: list[dict]) -> None:
        """Copy the demos of `records` (sorted by ep_id) from their shards into data/<category>.hdf5 as demo_k."""
        with (atomic_path(self.out_dir / "data" / f"{category}.hdf5") as temporary, h5py.File(temporary, "w") as out,
              contextlib.ExitStack() as stack):
            group = out.create_group("data")
            shards: dict[str, h5py.File] = {}
            for index, record in enumerate(records):
                if record["shard"] not in shards:
                    shards[record["shard"]] = stack.enter_context(h5py.File(self.out_dir / record["shard"], "r"))
                shards[record["shard"]].copy(f"data/{record['demo']}", group, name=f"demo_{index}")
            group.attrs["total"] = sum(r["steps"] for r in records)
            group.attrs["env_args"] = json.dumps(self.env_args)

    @contextlib.contextmanager
    def _locked(self):
        with open(self.out_dir / ".lock", "a") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            yield

    def _ledger(self) -> dict | None:
        return read_ledger(self.out_dir)

    def _write_ledger(self, ledger: dict) -> None:
        with atomic_write(self.out_dir / _LEDGER) as file:
            json.dump(ledger, file)

    def _remove_uncommitted(self, ledger: dict) -> None:
        """Delete shards and sidecars the ledger does not list, and temporaries of interrupted atomic writes."""
        keep = {self.out_dir / shard for shard in ledger["episodes"].values() if shard}
        keep |= {self.out_dir / "episodes" / f"{ep_id}.json" for ep_id in ledger["episodes"]}
        for path in [*self.out_dir.glob("shards/*/*"), *self.out_dir.glob("episodes/*")]:
            if path not in keep:
                path.unlink()
        for path in [*self.out_dir.glob(".*.tmp*"), *self.out_dir.glob("data/.*.tmp*")]:
            path.unlink()


def read_demos(path: str | os.PathLike) -> Iterator[tuple[str, dict]]:
    """(name, arrays) of each demo of a category file (or a shard) in order; arrays holds the datasets, 'obs' (a
    dict of the observation arrays) and 'attrs' (num_samples, ep_id, seed, task_type, split, obj_id, ...)."""
    with h5py.File(path, "r") as file:
        if "data" not in file:
            raise DataError(f"{path}: no 'data' group; not a demonstration file")
        for name in sorted(file["data"], key=lambda n: int(n.rsplit("_", 1)[1])):
            demo = file["data"][name]
            arrays = {key: value[()] for key, value in demo.items() if isinstance(value, h5py.Dataset)}
            arrays["obs"] = {key: value[()] for key, value in demo["obs"].items()}
            arrays["attrs"] = dict(demo.attrs)
            yield name, arrays


def load_sidecar(out_dir: str | os.PathLike, ep_id: int) -> dict:
    """The sidecar of a committed episode (see `_sidecar` for its fields); DataError if there is none."""
    path = Path(out_dir) / "episodes" / f"{ep_id}.json"
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError(f"{path}: no sidecar for episode {ep_id}") from None


def _category(episode: Episode) -> str:
    slug = category_slug(episode.obj_class)
    if slug not in CATEGORIES:
        raise DataError(f"episode {episode.ep_id}: unknown category '{episode.obj_class}'; expected one of "
                        f"{', '.join(CATEGORIES)}")
    return slug


def _check_layout(demo: Demo, layout: dict | None) -> dict:
    """The run's observation layout {key: [per-step shape, dtype]}; DataError if `demo` differs from it."""
    mine = {key: [list(value.shape[1:]), value.dtype.str] for key, value in sorted(demo.obs.items())}
    if layout is not None and mine != layout:
        key = next(k for k in sorted(set(mine) | set(layout)) if mine.get(k) != layout.get(k))
        raise DataError(f"episode {demo.episode.ep_id}: obs['{key}'] is {mine.get(key)} (per-step shape, dtype) "
                        f"but earlier demos of this run have {layout.get(key)}")
    return mine


def _write_demo(group: h5py.Group, demo: Demo) -> None:
    """One demo in robomimic layout; per-step arrays of arrays (clouds, images) in chunks of CHUNK_STEPS steps,
    byte-shuffled and lzf-compressed."""
    episode = demo.episode
    group.attrs.update(num_samples=demo.steps, ep_id=episode.ep_id, task_type=episode.task_type,
                       split=episode.split, obj_class=episode.obj_class, obj_id=episode.obj_id,
                       task_instruction=episode.task_instruction)
    if episode.seed is not None:
        group.attrs["seed"] = episode.seed
    group["actions"] = demo.actions
    group["skill_index"] = demo.skill_index
    group.create_dataset("skill_instructions", dtype=h5py.string_dtype(),
                         data=[episode.skill_instructions[i] for i in demo.skill_index])
    group["initial_state"] = demo.initial_state
    obs = group.create_group("obs")
    for key, value in demo.obs.items():
        if value.ndim >= 3:
            obs.create_dataset(key, data=value, chunks=(min(CHUNK_STEPS, len(value)), *value.shape[1:]),
                               compression="lzf", shuffle=True)
        else:
            obs[key] = value


def _sidecar(episode: Episode, demo: Demo | None, shard: str | None, failing_skill: str | None) -> dict:
    """The JSON record of one episode: its metadata, outcome and, for a success, where its demo is."""
    return {"ep_id": episode.ep_id, "seed": episode.seed, "obj_class": episode.obj_class, "obj_id": episode.obj_id,
            "task_type": episode.task_type, "split": episode.split,
            "chain_params": [step.to_metadata() for step in episode.chain],
            "task_instruction": episode.task_instruction, "skill_instructions": list(episode.skill_instructions),
            "obj_pose": list(episode.obj_pose), "obj_scale": episode.obj_scale,
            "success": demo is not None, "failing_skill": failing_skill,
            "steps": demo.steps if demo else None,
            "skill_boundaries": demo.skill_boundaries if demo else None,
            "initial_state": demo.initial_state.tolist() if demo else None,
            "shard": shard, "demo": f"ep_{episode.ep_id}" if demo else None}


def _episode(record: dict) -> Episode:
    return Episode(record["obj_class"], record["obj_id"], record["ep_id"], record["task_type"], record["split"],
                   tuple(SkillStep.from_metadata(entry) for entry in record["chain_params"]),
                   record["task_instruction"], tuple(record["skill_instructions"]), tuple(record["obj_pose"]),
                   record["obj_scale"], record["seed"])


def _summary(records: list[dict], by_category: dict[str, list[dict]]) -> dict:
    """Counts and success rates overall and per task type, failing-skill histograms, demos per category."""
    per_type: dict[str, dict] = {}
    for record in sorted(records, key=lambda r: r["task_type"]):
        entry = per_type.setdefault(str(record["task_type"]), {"episodes": 0, "successes": 0, "failures": 0,
                                                               "failing_skills": {}})
        entry["episodes"] += 1
        if record["success"]:
            entry["successes"] += 1
        else:
            entry["failures"] += 1
            skills = entry["failing_skills"]
            skills[record["failing_skill"]] = skills.get(record["failing_skill"], 0) + 1
    for entry in per_type.values():
        entry["success_rate"] = entry["successes"] / entry["episodes"]
        entry["failing_skills"] = dict(sorted(entry["failing_skills"].items()))
    successes = sum(r["success"] for r in records)
    return {"episodes": len(records), "successes": successes, "failures": len(records) - successes,
            "success_rate": successes / len(records) if records else None,
            "steps": sum(r["steps"] for r in records if r["success"]),
            "demos_per_category": {category: len(mine) for category, mine in sorted(by_category.items())},
            "per_task_type": per_type, "provenance": provenance()}
