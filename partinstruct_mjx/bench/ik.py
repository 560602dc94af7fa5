"""IK solves per second: the batched JAX solver on the current JAX device against the mink reference on a CPU.

Both solve the same kinds of targets: TCP poses of random arm configurations over the table near the objects
(pointing down), reached either by closed-loop servoing (seeded a few cm / degrees away) or from the home pose.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from partinstruct_mjx.bench.timing import Throughput, measure_throughput
from partinstruct_mjx.control import jax_ik
from partinstruct_mjx.control.mink_ik import MinkIK
from partinstruct_mjx.control.scripted_pick import top_down_quat
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import Scene

POSITION_TOLERANCE = 1e-3
ROTATION_TOLERANCE = 1e-2
TARGET_KINDS = ("servo", "from home")


@dataclass(frozen=True)
class Targets:
    """IK problems: seeds (N, 7), TCP positions (N, 3) and orientations (N, 4) (w, x, y, z)."""

    kind: str
    seeds: np.ndarray
    pos: np.ndarray
    quat: np.ndarray

    def tiled(self, count: int) -> Targets:
        """The first `count` problems, repeating the set as often as needed."""
        index = np.arange(count) % len(self.seeds)
        return Targets(self.kind, self.seeds[index], self.pos[index], self.quat[index])


@dataclass(frozen=True)
class JaxResult:
    batch_size: int
    timing: Throughput
    """Solves per second."""


@dataclass(frozen=True)
class AccuracyResult:
    kind: str
    count: int
    jax_solved: float
    """Fraction of targets the JAX solver reaches within 1 mm and 0.01 rad."""
    mink_solved: float
    mink_count: int
    mink_solves_per_s: float


@dataclass(frozen=True)
class IKBenchResults:
    device: str
    config: jax_ik.IKConfig
    speed: list[JaxResult]
    accuracy: list[AccuracyResult]


def make_targets(scene: Scene, kind: str, count: int, seed: int = 0) -> Targets:
    """`count` reachable targets of `kind` ("servo" or "from home"), made by MuJoCo FK of in-limit configurations."""
    if kind not in TARGET_KINDS:
        raise ValueError(f"target kind must be one of {TARGET_KINDS}, got {kind!r}")
    rng = np.random.default_rng(seed)
    lower, upper = scene.model.jnt_range[scene.arm_qpos_adr].T
    if kind == "servo":
        goals = workspace_configs(scene, count, lambda: rng.uniform(lower, upper))
        seeds = np.clip(goals + rng.normal(0.0, 0.05, goals.shape), lower, upper)
    else:
        grasp = MinkIK(scene).solve(panda.HOME_ARM_QPOS, np.array([0.0, 0.05, 0.15]), top_down_quat(0.3)).arm_qpos
        goals = workspace_configs(scene, count, lambda: grasp + rng.uniform(-0.3, 0.3, grasp.shape))
        seeds = np.tile(panda.HOME_ARM_QPOS, (count, 1))
    data = mujoco.MjData(scene.model)
    pos, quat = [], []
    for q in goals:
        data.qpos[scene.arm_qpos_adr] = q
        mujoco.mj_kinematics(scene.model, data)
        pos.append(data.site_xpos[scene.tcp_site].copy())
        quat.append(data.xquat[scene.hand_body].copy())
    return Targets(kind, seeds, np.array(pos), np.array(quat))


def workspace_configs(scene: Scene, count: int, sample: Callable[[], np.ndarray]) -> np.ndarray:
    """Configurations from `sample()`, clipped to the limits, with the TCP over the table near objects, facing down."""
    data = mujoco.MjData(scene.model)
    lower, upper = scene.model.jnt_range[scene.arm_qpos_adr].T
    configs = []
    while len(configs) < count:
        q = np.clip(sample(), lower, upper)
        data.qpos[scene.arm_qpos_adr] = q
        mujoco.mj_kinematics(scene.model, data)
        x, y, z = data.site_xpos[scene.tcp_site]
        if -0.15 < x < 0.2 and -0.2 < y < 0.3 and 0.07 < z < 0.4 and data.site_xmat[scene.tcp_site][8] < -0.5:
            configs.append(q)
    return np.array(configs)


def measure_jax(kin: jax_ik.ArmKinematics, targets: Targets, batch_size: int, config: jax_ik.IKConfig,
                repeats: int, min_solves: int = 2048) -> JaxResult:
    """Time `solve_ik` at one batch size (caches cleared first); each repeat runs calls for `min_solves` solves."""
    batch = targets.tiled(batch_size)
    args = [jax.device_put(jnp.asarray(a)) for a in (batch.seeds, batch.pos, batch.quat)]
    timing = measure_throughput(lambda: jax_ik.solve_ik(kin, *args, config)[0], batch_size, repeats, min_solves)
    return JaxResult(batch_size, timing)


def reached(kin: jax_ik.ArmKinematics, targets: Targets, config: jax_ik.IKConfig) -> np.ndarray:
    """Whether the JAX solver, on the whole set as one batch, puts the TCP within 1 mm and 0.01 rad of each target."""
    _, pos_err, rot_err = jax_ik.solve_ik(kin, targets.seeds, targets.pos, targets.quat, config)
    return (np.asarray(pos_err) < POSITION_TOLERANCE) & (np.asarray(rot_err) < ROTATION_TOLERANCE)


def measure_mink(scene: Scene, targets: Targets) -> tuple[float, np.ndarray]:
    """mink solves/s over the targets (one solve after another) and whether each target was reached."""
    ik = MinkIK(scene)
    start = time.perf_counter()
    solutions = [ik.solve(*problem) for problem in zip(targets.seeds, targets.pos, targets.quat)]
    rate = len(solutions) / (time.perf_counter() - start)
    solved = np.array([s.position_error < POSITION_TOLERANCE and s.rotation_error < ROTATION_TOLERANCE
                       for s in solutions])
    return rate, solved


def run(scene: Scene, batch_sizes: tuple[int, ...] = (1, 64, 1024, 16384), config: jax_ik.IKConfig = jax_ik.IKConfig(),
        repeats: int = 5, accuracy_count: int = 1024, mink_count: int = 100, seed: int = 0) -> IKBenchResults:
    """Speed of the JAX solver at each batch size (servo targets) and, per target kind, how many targets the JAX
    solver (batch `accuracy_count`) and mink (the first `mink_count`) reach, with mink's solves/s."""
    kin = jax_ik.ArmKinematics.from_scene(scene)
    pools = {kind: make_targets(scene, kind, accuracy_count, seed) for kind in TARGET_KINDS}
    speed = [measure_jax(kin, pools["servo"], size, config, repeats) for size in batch_sizes]
    accuracy = []
    for kind, pool in pools.items():
        jax_solved = reached(kin, pool, config)
        mink_rate, mink_solved = measure_mink(scene, pool.tiled(min(mink_count, accuracy_count)))
        accuracy.append(AccuracyResult(kind, accuracy_count, float(jax_solved.mean()), float(mink_solved.mean()),
                                       len(mink_solved), mink_rate))
    device = jax.devices()[0]
    name = "CPU" if device.platform == "cpu" else device.device_kind
    return IKBenchResults(name, config, speed, accuracy)


def markdown(results: IKBenchResults) -> str:
    """Two tables: JAX IK speed per batch size, and reached targets / mink speed per target kind."""
    cfg = results.config
    speed = "\n".join(
        f"| {r.batch_size:,} | {r.timing.cells()} |"
        for r in results.speed)
    accuracy = "\n".join(
        f"| {r.kind} | {r.jax_solved:.1%} of {r.count:,} | {r.mink_solved:.1%} of {r.mink_count:,} | "
        f"{r.mink_solves_per_s:,.0f} |" for r in results.accuracy)
    return (
        f"Batched JAX damped-least-squares IK (`partinstruct_mjx/control/jax_ik.py`) on {results.device}: "
        f"at most {cfg.iterations} iterations per solve, stopping below a weighted pose error of {cfg.tolerance:g} "
        f"(a batch runs until all of its solves have stopped), damping {cfg.damping:g} + {cfg.error_damping:g} |e|^2, "
        f"max step {cfg.max_step:g} rad, orientation weight {cfg.orientation_weight:g} m/rad. Targets are TCP poses "
        f"of random arm configurations over the table near the objects; 'servo' seeds are those configurations plus "
        f"0.05 rad (3 deg) of noise per joint, 'from home' seeds are the home pose; speed is measured on servo "
        f"targets (3 deg from the solution: the closed-loop case of an env step). Reached = within 1 mm and 0.01 "
        f"rad. mink (`control/mink_ik.py`, up to 300 QP iterations until 0.1 mm / 0.001 rad) runs one target after another on "
        f"one CPU thread.\n\n"
        "| batch | JAX solves/s (median) | range over repeats | compile s |\n|---|---|---|---|\n" + speed + "\n\n"
        "| targets | JAX reached | mink reached | mink solves/s |\n|---|---|---|---|\n" + accuracy + "\n")
