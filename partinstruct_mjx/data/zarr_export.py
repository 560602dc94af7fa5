"""Export a demos run directory to one zarr store in 3D Diffusion Policy's layout.

DP3 (and Diffusion Policy) train from a zarr "replay buffer": every step of every demo stacked along the first axis
under data/, and meta/episode_ends, the exclusive end index of each demo. The store is zarr format 2 (what DP3's
zarr 2 reads; zarr 3 reads it too), compressed with Blosc/zstd as DP3's own data is:

  data/point_cloud       (N, 1024, 3) float32   obs/agentview_pcd
  data/part_point_cloud  (N, 1024, 4) float32   obs/agentview_part_pcd (xyz + target-part flag, the -S input)
  data/state             (N, 15) float32        tcp_pose, joint_states, gripper_state side by side (DP3's agent_pos)
  data/<key>             every other observation (tcp_pose, joint_states, gripper_state, object_pose) as stored
  data/action            (N, 7) float32         the absolute 7-D actions
  data/skill_index       (N,) int32             the chain skill each step executes
  meta/episode_ends      (E,) int64
  meta/ep_id, meta/task_type, meta/seed  (E,) int64
  attrs: 'episodes' (per demo: ep_id, category, obj_id, split, task_type, task_instruction, skill_instructions),
         'env_args' of the run, 'source' (the run directory)
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py
import numpy as np

from partinstruct_mjx.data.demos import demo_files, read_demos
from partinstruct_mjx.errors import DataError

RENAMED = {"agentview_pcd": "point_cloud", "agentview_part_pcd": "part_point_cloud"}
"""Observation keys stored under DP3's names."""
STATE_KEYS = ("tcp_pose", "joint_states", "gripper_state")
"""Observations joined, in this order, into data/state."""
CHUNK_BYTES = 4 << 20
"""Target size of one chunk before compression (chunks run along the steps)."""
EPISODE_META = ("ep_id", "task_type", "seed")


def export_zarr(run_dir: str | os.PathLike, out: str | os.PathLike, categories=None, progress: bool = True) -> dict:
    """Write the demos of `run_dir` (all categories, or those named) to the zarr store `out`, which must not exist.
    Written under a temporary name and renamed when complete, so an interrupted export leaves nothing behind.
    Returns {'demos', 'steps', 'path'}."""
    try:
        import zarr
    except ImportError:
        raise DataError('the zarr export needs the zarr package: pip install "partinstruct-mjx[zarr]"') from None
    run_dir, out = Path(run_dir), Path(out)
    files = _category_files(run_dir, categories)
    if out.exists():
        raise DataError(f"{out} already exists; remove it or choose another path")
    lengths = _demo_lengths(files)
    temporary = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    shutil.rmtree(temporary, ignore_errors=True)
    try:
        root = zarr.open_group(temporary, mode="w", zarr_format=2)
        columns, ends, episodes, meta = {}, [], [], {key: [] for key in EPISODE_META}
        with _progress(len(lengths), progress) as bar:
            for path in files:
                for _, demo in read_demos(path):
                    steps = _steps(demo)
                    for key, value in steps.items():
                        if key not in columns:
                            columns[key] = _Column(root, key, value, sum(lengths))
                        columns[key].append(value)
                    ends.append((ends[-1] if ends else 0) + len(steps["action"]))
                    episodes.append(_episode_record(demo, path.stem))
                    for key in EPISODE_META:
                        meta[key].append(int(demo["attrs"][key]))
                    bar.update(1)
        for column in columns.values():
            column.close()
        group = root.require_group("meta")
        for key, values in {"episode_ends": ends, **meta}.items():
            group.create_array(key, data=np.asarray(values, np.int64))
        root.attrs.update({"episodes": episodes, "env_args": _env_args(files[0]), "source": str(run_dir.resolve())})
        os.replace(temporary, out)
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise
    return {"demos": len(ends), "steps": int(ends[-1]) if ends else 0, "path": str(out)}


class _Column:
    """One data/ array, written a whole chunk at a time as the demos' steps arrive (no chunk is written twice)."""

    def __init__(self, root, key: str, first: np.ndarray, total: int):
        import numcodecs

        row_bytes = max(first[0].nbytes, 1)
        self.rows = max(1, min(total, CHUNK_BYTES // row_bytes))
        self.array = root.require_group("data").create_array(
            key, shape=(total, *first.shape[1:]), chunks=(self.rows, *first.shape[1:]), dtype=first.dtype,
            compressors=numcodecs.Blosc(cname="zstd", clevel=3, shuffle=numcodecs.Blosc.SHUFFLE))
        self.pending: list[np.ndarray] = []
        self.written = 0

    def append(self, value: np.ndarray) -> None:
        self.pending.append(value)
        if sum(len(v) for v in self.pending) >= self.rows:
            self._flush(final=False)

    def close(self) -> None:
        self._flush(final=True)

    def _flush(self, final: bool) -> None:
        block = np.concatenate(self.pending)
        whole = len(block) if final else len(block) // self.rows * self.rows
        self.array[self.written:self.written + whole] = block[:whole]
        self.written += whole
        self.pending = [block[whole:]]


def _steps(demo: dict) -> dict[str, np.ndarray]:
    """The per-step arrays of one demo, under their data/ names."""
    obs = demo["obs"]
    missing = [key for key in STATE_KEYS if key not in obs]
    if missing:
        raise DataError(f"demo {demo['attrs'].get('ep_id')}: no obs/{', obs/'.join(missing)} to build data/state")
    steps = {RENAMED.get(key, key): value for key, value in obs.items()}
    steps["state"] = np.concatenate([obs[key].astype(np.float32) for key in STATE_KEYS], axis=-1)
    steps["action"] = demo["actions"]
    steps["skill_index"] = demo["skill_index"]
    return steps


def _episode_record(demo: dict, category: str) -> dict:
    """A demo's episode: its attributes and the instruction of each chain skill (from the per-step ones)."""
    attrs = demo["attrs"]
    skills: dict[int, str] = {}
    for index, text in zip(demo["skill_index"], demo["skill_instructions"]):
        skills.setdefault(int(index), text.decode() if isinstance(text, bytes) else str(text))
    return {"ep_id": int(attrs["ep_id"]), "category": category, "obj_id": str(attrs["obj_id"]),
            "split": str(attrs["split"]), "task_type": int(attrs["task_type"]),
            "task_instruction": str(attrs["task_instruction"]), "skill_instructions": [skills[k] for k in sorted(skills)]}


def _category_files(run_dir: Path, categories) -> list[Path]:
    """The run's per-category HDF5 files, those of `categories` only if given."""
    files = demo_files(run_dir)
    if categories:
        unknown = sorted(set(categories) - {path.stem for path in files})
        if unknown:
            raise DataError(f"{run_dir}: no demos of {', '.join(unknown)}; it holds {', '.join(p.stem for p in files)}")
        files = [path for path in files if path.stem in set(categories)]
    return files


def _demo_lengths(files: list[Path]) -> list[int]:
    """Steps of every demo of the files (their num_samples attributes; the arrays are not read)."""
    lengths = []
    for path in files:
        with h5py.File(path, "r") as file:
            if "data" not in file:
                raise DataError(f"{path}: no 'data' group; not a demonstration file")
            lengths += [int(group.attrs["num_samples"]) for group in file["data"].values()]
    return lengths


def _env_args(path: Path) -> dict:
    with h5py.File(path, "r") as file:
        raw = file["data"].attrs.get("env_args", "{}")
    return json.loads(raw)


def _progress(total: int, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="demo", desc="zarr", disable=not enabled)
