"""Demonstrations as training windows: load a `partinstruct demos` directory into memory, normalise, sample batches.

Every demo's steps are concatenated along time in NumPy arrays (clouds as float16 to halve the memory; they are
camera-frame metres, so the rounding is under a millimetre). A window is `horizon` consecutive steps of one demo,
starting `obs_steps - 1` steps before to `action_steps - 1` steps after the demo's ends, padded by repeating the
first or last step (diffusion_policy's SequenceSampler). Batches are drawn from a fixed, seeded sequence of epoch
permutations, so batch k is the same whether or not training was interrupted before it.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from partinstruct_mjx.atomic import atomic_path
from partinstruct_mjx.data.demos import ACTION_SIZE, demo_files
from partinstruct_mjx.errors import DataError
from partinstruct_mjx.train import features
from partinstruct_mjx.train.config import CLOUD_CHANNELS, ModelConfig


@dataclass
class DemoData:
    """All demos of a data directory, concatenated along time (S steps in all, E demos)."""

    clouds: np.ndarray
    """(S, N, C) float16 point clouds in the camera's optical frame."""
    proprio: np.ndarray
    """(S, 17) float32 proprioception features (features.proprio_features)."""
    actions: np.ndarray
    """(S, 10) float32 network actions (features.actions_to_model)."""
    instruction_ids: np.ndarray
    """(S,) int32 row of `instructions` that labels each step."""
    instructions: list[str]
    episode_ends: np.ndarray
    """(E,) exclusive end step of each demo."""
    sampler: str
    """Point-cloud sampler the demos were rendered with ('stride' or 'fps')."""
    files: list[str]

    @property
    def episode_starts(self) -> np.ndarray:
        return np.concatenate([[0], self.episode_ends[:-1]]).astype(np.int64)

    def summary(self) -> dict:
        """What a run was trained on (recorded in config.json; a resumed run must see the same)."""
        return {"files": self.files, "demos": len(self.episode_ends), "steps": int(self.episode_ends[-1]),
                "instructions": len(self.instructions), "pcd_sampler": self.sampler,
                "cloud_shape": list(self.clouds.shape[1:])}


def load_demos(data_dir: str | os.PathLike, cloud_key: str, instructions: str = "skill",
               progress: bool = False) -> DemoData:
    """Read every demo of `data_dir`/data/*.hdf5 (only `cloud_key` of the clouds) into one DemoData.

    `instructions` is 'skill' (each step's skill instruction) or 'task' (the episode's task instruction). DataError
    for no demos, missing or malformed datasets, or files rendered with different point-cloud samplers.
    """
    from tqdm import tqdm

    files = demo_files(data_dir)
    samplers = {path: _pcd_sampler(path) for path in files}
    if len(set(samplers.values())) > 1:
        raise DataError(f"{data_dir}: files rendered with different point-cloud samplers: "
                        + ", ".join(f"{p.name} {s}" for p, s in samplers.items()))
    demos = _demo_index(files, cloud_key)
    if not demos:
        raise DataError(f"{data_dir}: the files {', '.join(p.name for p in files)} hold no demos")
    ends = np.cumsum([steps for _, _, steps, _ in demos])
    clouds = np.empty((int(ends[-1]), *demos[0][3]), np.float16)  # filled in place: the clouds are most of the memory
    texts: dict[str, int] = {}
    parts: dict[str, list[np.ndarray]] = {key: [] for key in ("actions", "instruction_ids", *features.PROPRIO_KEYS)}
    with tqdm(total=len(demos), desc="loading demos", unit="demo", disable=not progress) as bar:
        for path, mine in itertools.groupby(enumerate(demos), key=lambda item: item[1][0]):
            with _open(path) as file:
                for index, (_, name, _, _) in mine:
                    group = file["data"][name]
                    demo = _read_demo(path, name, group, cloud_key, instructions)
                    if demo["clouds"].shape[1:] != clouds.shape[1:]:
                        raise DataError(f"{path}: data/{name}/obs/{cloud_key} has {demo['clouds'].shape[1:]} points "
                                        f"per step; earlier demos have {clouds.shape[1:]}")
                    clouds[ends[index] - len(demo["actions"]):ends[index]] = demo["clouds"]
                    for key in parts.keys() - {"instruction_ids"}:
                        parts[key].append(demo[key])
                    parts["instruction_ids"].append(
                        np.array([texts.setdefault(text, len(texts)) for text in demo["texts"]], np.int32))
                    bar.update()
    joined = {key: np.concatenate(value) for key, value in parts.items()}
    return DemoData(
        clouds=clouds,
        proprio=np.asarray(features.proprio_features(*(joined[key] for key in features.PROPRIO_KEYS))),
        actions=np.asarray(features.actions_to_model(joined["actions"])),
        instruction_ids=joined["instruction_ids"], instructions=list(texts), episode_ends=ends.astype(np.int64),
        sampler=next(iter(samplers.values())), files=[str(p) for p in files])


def _demo_index(files: list[Path], cloud_key: str) -> list[tuple[Path, str, int, tuple[int, ...]]]:
    """(file, demo name, steps, per-step cloud shape) of every demo, in file and demo order, read from the headers."""
    demos = []
    for path in files:
        with _open(path) as file:
            for name in sorted(file["data"], key=lambda n: int(n.rsplit("_", 1)[1])):
                group = file["data"][name]
                if "actions" not in group or f"obs/{cloud_key}" not in group:
                    raise DataError(f"{path}: data/{name} has no actions or no obs/{cloud_key}")
                demos.append((path, name, len(group["actions"]), group[f"obs/{cloud_key}"].shape[1:]))
    return demos


def _pcd_sampler(path: Path) -> str:
    """The point-cloud sampler recorded in a file's env_args (written by `partinstruct demos`)."""
    with _open(path) as file:
        try:
            return json.loads(file["data"].attrs["env_args"])["synthesis"]["pcd_sampler"]
        except (KeyError, TypeError, ValueError):
            raise DataError(f"{path}: data.attrs['env_args'] does not name the point-cloud sampler "
                            "(synthesis.pcd_sampler); was it written by `partinstruct demos`?") from None


@contextlib.contextmanager
def _open(path: Path) -> Iterator[h5py.File]:
    """A demonstration file open for reading; DataError if it is unreadable or has no 'data' group."""
    try:
        file = h5py.File(path, "r")
    except OSError as err:
        raise DataError(f"{path}: not a readable HDF5 file ({err})") from None
    with file:
        if "data" not in file:
            raise DataError(f"{path}: no 'data' group; not a demonstration file")
        yield file


def _read_demo(path: Path, name: str, group: h5py.Group, cloud_key: str, instructions: str) -> dict:
    """The arrays of one demo a policy needs, checked against the actions' length."""
    where = f"{path}: data/{name}"
    try:
        actions = group["actions"][()]
        obs = {key: group["obs"][key][()] for key in (cloud_key, *features.PROPRIO_KEYS)}
        if instructions == "skill":
            texts = [t.decode() if isinstance(t, bytes) else str(t) for t in group["skill_instructions"][()]]
        else:
            texts = [str(group.attrs["task_instruction"])] * len(actions)
    except KeyError as err:
        raise DataError(f"{where}: missing {err.args[0] if err.args else 'dataset'} (actions, skill_instructions, "
                        f"obs/{cloud_key}, obs/tcp_pose, obs/joint_states and obs/gripper_state are needed)") from None
    steps = len(actions)
    expected = {"actions": (steps, ACTION_SIZE), "tcp_pose": (steps, 7), "joint_states": (steps, 7),
                "gripper_state": (steps, 1)}
    shapes = {"actions": actions.shape, **{key: obs[key].shape for key in features.PROPRIO_KEYS}}
    for key, shape in expected.items():
        if shapes[key] != shape or steps == 0:
            raise DataError(f"{where}: {key} has shape {shapes[key]}; expected {shape} with at least one step")
    cloud = obs[cloud_key]
    if cloud.ndim != 3 or len(cloud) != steps or cloud.shape[2] != CLOUD_CHANNELS[cloud_key]:
        raise DataError(f"{where}: obs/{cloud_key} has shape {cloud.shape}; expected ({steps}, N, "
                        f"{CLOUD_CHANNELS[cloud_key]})")
    if len(texts) != steps:
        raise DataError(f"{where}: {len(texts)} skill_instructions for {steps} steps")
    return {"clouds": cloud.astype(np.float16), "actions": actions, "texts": texts,
            **{key: obs[key] for key in features.PROPRIO_KEYS}}


def split_episodes(num_episodes: int, val_ratio: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, validation) demo indices: round(val_ratio * E) held out, at least one and never all (diffusion_policy's
    get_val_mask); none when val_ratio is 0 or there is a single demo."""
    held_out = 0 if val_ratio <= 0 else min(max(1, round(num_episodes * val_ratio)), num_episodes - 1)
    order = np.random.default_rng(seed).permutation(num_episodes)
    return np.sort(order[held_out:]), np.sort(order[:held_out])


@dataclass(frozen=True)
class Normalizer:
    """Per-dimension affine map of actions and proprioception onto [-1, 1] from their min and max (dimensions that
    never change map to 0, as diffusion_policy's LinearNormalizer does)."""

    action_scale: np.ndarray
    action_offset: np.ndarray
    proprio_scale: np.ndarray
    proprio_offset: np.ndarray

    @classmethod
    def fit(cls, actions: np.ndarray, proprio: np.ndarray) -> Normalizer:
        return cls(*_limits(actions), *_limits(proprio))

    def actions(self, x):
        return x * self.action_scale + self.action_offset

    def actions_back(self, x):
        return (x - self.action_offset) / self.action_scale

    def proprio(self, x):
        return x * self.proprio_scale + self.proprio_offset

    def save(self, path: str | os.PathLike) -> None:
        with atomic_path(path) as temporary:
            np.savez(temporary, **{k: getattr(self, k) for k in self.__dataclass_fields__})

    @classmethod
    def load(cls, path: str | os.PathLike) -> Normalizer:
        try:
            with np.load(path) as file:
                return cls(**{k: file[k].astype(np.float32) for k in cls.__dataclass_fields__})
        except (OSError, KeyError, ValueError) as err:
            raise DataError(f"{path}: not a normalizer file ({err})") from None


def _limits(x: np.ndarray, eps: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    low, high = x.min(axis=0), x.max(axis=0)
    span = high - low
    constant = span < eps
    scale = np.where(constant, 1.0, 2.0 / np.where(constant, 1.0, span))
    offset = np.where(constant, -low, -1.0 - scale * low)
    return scale.astype(np.float32), offset.astype(np.float32)


class WindowSampler:
    """Fixed-shape, normalised training batches of windows of the chosen demos.

    A batch is a dict: clouds (B, obs_steps, N, C) float32, proprio (B, obs_steps, 17), instruction (B, 256) of
    the window's current step (its last observation step), actions (B, horizon, 10).
    """

    def __init__(self, data: DemoData, episodes: np.ndarray, normalizer: Normalizer, instruction_vectors: np.ndarray,
                 model: ModelConfig, batch_size: int, seed: int):
        self.data = data
        self.normalizer = normalizer
        self.instruction_vectors = instruction_vectors
        self.model = model
        self.batch_size = batch_size
        self.seed = seed
        self.first, self.low, self.high = window_index(data.episode_starts[episodes], data.episode_ends[episodes],
                                                       model.horizon, model.obs_steps - 1, model.action_steps - 1)
        if not len(self.first):
            raise DataError(f"the demos hold no window of {model.horizon} steps")

    def __len__(self) -> int:
        return len(self.first)

    def steps(self, windows: np.ndarray) -> np.ndarray:
        """(W, horizon) global step of each position of `windows`, padded by repetition at the demo's ends."""
        return np.clip(self.first[windows, None] + np.arange(self.model.horizon), self.low[windows, None],
                       self.high[windows, None])

    def windows(self, step: int) -> np.ndarray:
        """(batch_size,) windows of training batch `step`: positions [step * B, (step + 1) * B) of the endless
        sequence of seeded epoch permutations."""
        count = len(self)
        positions = step * self.batch_size + np.arange(self.batch_size)
        epochs = positions // count
        out = np.empty(self.batch_size, np.int64)
        for epoch in np.unique(epochs):
            order = np.random.default_rng((self.seed, int(epoch))).permutation(count)
            mine = epochs == epoch
            out[mine] = order[positions[mine] % count]
        return out

    def batch(self, step: int) -> dict[str, np.ndarray]:
        return self.assemble(self.windows(step))

    def assemble(self, windows: np.ndarray) -> dict[str, np.ndarray]:
        """The batch of the given windows (any count)."""
        steps = self.steps(windows)
        observed = steps[:, :self.model.obs_steps]
        return {"clouds": self.data.clouds[observed].astype(np.float32),
                "proprio": self.normalizer.proprio(self.data.proprio[observed]).astype(np.float32),
                "instruction": self.instruction_vectors[self.data.instruction_ids[observed[:, -1]]],
                "actions": self.normalizer.actions(self.data.actions[steps]).astype(np.float32)}

    def validation_batches(self, max_batches: int) -> list[tuple[dict[str, np.ndarray], np.ndarray]]:
        """Fixed batches over every window (a seeded subset beyond max_batches full batches), each with a (B,)
        weight that is 0 for the repeated windows padding the last batch."""
        windows = np.arange(len(self))
        if len(windows) > max_batches * self.batch_size:
            windows = np.sort(np.random.default_rng(self.seed).choice(windows, max_batches * self.batch_size,
                                                                      replace=False))
        batches = []
        for first in range(0, len(windows), self.batch_size):
            chunk = windows[first:first + self.batch_size]
            weight = np.zeros(self.batch_size, np.float32)
            weight[:len(chunk)] = 1.0
            batches.append((self.assemble(np.resize(chunk, self.batch_size)), weight))
        return batches


def window_index(starts: np.ndarray, ends: np.ndarray, horizon: int, pad_before: int,
                 pad_after: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(first, low, high) per window: its first global step (may lie before its demo) and its demo's first and last
    step. A demo of L steps has L - horizon + pad_before + pad_after + 1 windows (none if that is not positive)."""
    first, low, high = [], [], []
    for start, end in zip(starts, ends):
        offsets = np.arange(-pad_before, end - start - horizon + pad_after + 1)
        first.append(start + offsets)
        low.append(np.full(len(offsets), start))
        high.append(np.full(len(offsets), end - 1))
    if not first:
        return (np.zeros(0, np.int64),) * 3
    return np.concatenate(first), np.concatenate(low), np.concatenate(high)
