"""Environment steps per second of the `mujoco` (C, CPU threads) backend at several batch sizes."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
from partinstruct_mjx.sim.scene import Scene


@dataclass(frozen=True)
class CpuBackendResult:
    batch_size: int
    threads: int
    env_steps_per_s: float
    """Median over repeats."""
    spread: tuple[float, float]
    """Slowest and fastest repeat, env steps/s."""


def moving_controls(batch_size: int, steps: int, seed: int = 0) -> np.ndarray:
    """(steps, B, 8) joint targets that sweep every arm joint around home and open/close the gripper."""
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, (batch_size, panda.NUM_ARM_JOINTS))
    t = np.arange(steps)[:, None, None] * 0.05
    arm = panda.HOME_ARM_QPOS + 0.3 * np.sin(2 * np.pi * 0.25 * t + phase)
    gripper = np.where((np.arange(steps) // 40) % 2 == 0, panda.FINGER_OPEN, panda.FINGER_CLOSED)
    gripper = np.broadcast_to(gripper[:, None, None], (steps, batch_size, 1))
    return np.concatenate([arm, gripper], axis=-1)


def measure(scene: Scene, batch_size: int, steps: int, repeats: int, threads: int | None) -> CpuBackendResult:
    """Time `steps` control steps of a batch (after reset), `repeats` times; reset time is not counted."""
    controls = moving_controls(batch_size, steps)
    rates = []
    with MujocoBackend(scene, batch_size, num_threads=threads) as backend:
        for _ in range(repeats):
            backend.reset()
            start = time.perf_counter()
            for ctrl in controls:
                backend.step(ctrl)
            rates.append(batch_size * steps / (time.perf_counter() - start))
        used_threads = len(backend._chunks)
    return CpuBackendResult(batch_size, used_threads, float(np.median(rates)), (min(rates), max(rates)))


def markdown(results: list[CpuBackendResult], scene: Scene) -> str:
    cfg = scene.config
    rows = "\n".join(
        f"| {r.batch_size} | {r.threads} | {r.env_steps_per_s:,.0f} | {r.env_steps_per_s * cfg.substeps:,.0f} | "
        f"{r.spread[0]:,.0f} - {r.spread[1]:,.0f} |" for r in results)
    return (
        f"Panda + `{scene.object_xml.parent.name}` object, {cfg.substeps} physics substeps of {cfg.timestep * 1000:g} ms "
        f"per 20 Hz env step; arm sweeping around home, gripper opening and closing; the state (poses, finger "
        f"contacts with forces) is gathered every step. No IK or predicates yet.\n\n"
        "| batch | threads | env steps/s (median) | physics steps/s | range over repeats |\n|---|---|---|---|---|\n"
        + rows + "\n")
