"""MJX env steps per second: `BraxPartInstructEnv.step` (IK, MJX physics substeps, state extraction, task progress,
observation), vmapped over a batch and jitted, on the current JAX device.

Per object and batch size on MJX's JAX implementation; on the object with the most collision hulls, variants of
its compiled model that only change what collides (the collision budget, DESIGN.md) or the constraint solver's
iteration caps; then per object and batch size on MuJoCo Warp (`impl="warp"`) when warp-lang is installed and a CUDA
GPU is present. Each jitted call scans `steps` env steps; the TCP targets circle 5 cm around the settled TCP while
the gripper opens and closes, so IK and contacts do real work.
"""

from __future__ import annotations

import contextlib
import copy
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from partinstruct_mjx.bench.report import env_row
from partinstruct_mjx.bench.timing import Throughput, measure_throughput
from partinstruct_mjx.env import EnvConfig, hold_action
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import Scene, SceneConfig, build_scene, random_placements
from partinstruct_mjx.tasks.episodes import Episode
from partinstruct_mjx.tasks.task_types import task_type

DEFAULT_BATCH_SIZES = (256, 1024, 4096, 16384)
TARGET_BATCH = 4096
TARGET_STEPS_PER_S = 100_000
TARGET_COMPILE_S = 60.0
"""DESIGN.md: >= 100,000 env steps/s at batch 4,096 with compile < 60 s on one H100."""
IMPLS = ("jax", "warp")
"""MJX implementations the suite measures."""
EPISODES = 8
"""Distinct pre-settled episodes (placements); the batch cycles through them."""
CIRCLE_RADIUS = 0.05
GRIPPER_PERIOD = 20
"""Env steps of one TCP circle (one jitted call at the default 20 steps); the gripper is closed in its second half."""


@dataclass(frozen=True)
class Variant:
    """A change of the compiled scene model that only alters what collides or how long the solver iterates (a timing
    probe, not a scene to use)."""

    name: str
    edit: Callable[[Scene, mujoco.MjModel], None]
    """Edits the model (a copy of `scene.model`) in place."""


def _robot_geoms(scene: Scene, model: mujoco.MjModel) -> np.ndarray:
    """Mask of the robot's geoms (everything but the object and the table)."""
    return (scene.geom_part < 0) & (np.arange(model.ngeom) != scene.table_geom)


def _grasp_pairs_only(scene: Scene, model: mujoco.MjModel) -> None:
    """Only finger pads-object and object-table: arm links and the hand collide with nothing, pads not with the
    table."""
    pads = scene.geom_finger >= 0
    robot = _robot_geoms(scene, model)
    model.geom_contype[robot & ~pads] = 0
    model.geom_conaffinity[robot & ~pads] = 0
    model.geom_conaffinity[pads & (model.geom_contype > 0)] = 2  # the object's contype bit only


def _half_the_hulls(scene: Scene, model: mujoco.MjModel) -> None:
    """All pairs as built, but only the first half of the object's hulls collide."""
    off = scene.object_geoms[(len(scene.object_geoms) + 1) // 2:]
    model.geom_contype[off] = 0
    model.geom_conaffinity[off] = 0


def _object_table_only(scene: Scene, model: mujoco.MjModel) -> None:
    """Only object-table: the robot collides with nothing (what the gripper's contacts cost; a model without any
    contacts cannot be measured, `extract_state` keeps the strongest MAX_FINGER_CONTACTS contact slots)."""
    robot = _robot_geoms(scene, model)
    model.geom_contype[robot] = 0
    model.geom_conaffinity[robot] = 0


def _short_line_search(scene: Scene, model: mujoco.MjModel) -> None:
    """All pairs as built, 4 line-search iterations instead of 10: under vmap MJX's line search runs all of its
    iterations in every environment (converged ones as no-ops), so the cap is its cost."""
    model.opt.ls_iterations = 4


def _one_newton_iteration(scene: Scene, model: mujoco.MjModel) -> None:
    """`_short_line_search` and a single Newton iteration per physics step (no loop)."""
    _short_line_search(scene, model)
    model.opt.iterations = 1


AS_BUILT = "as built: arm links-table, hand and pads-table and -object, object-table"
"""The scene's own collision set (DESIGN.md), measured at every batch size."""
VARIANTS = (
    Variant("pads-object and object-table only", _grasp_pairs_only),
    Variant("as built, half of the object's hulls collide", _half_the_hulls),
    Variant("object-table only", _object_table_only),
    Variant("as built, line search 4 iterations", _short_line_search),
    Variant("as built, line search 4, 1 Newton iteration", _one_newton_iteration),
)
"""Collision- and solver-budget variants measured on the object with the most hulls, besides AS_BUILT."""


@dataclass(frozen=True)
class Row:
    object_name: str
    variant: str
    impl: str
    batch_size: int
    hulls: int
    """Colliding object hulls."""
    contacts: int | None
    """MJX contact slots per environment (fixed by the collision set, all evaluated every substep); None for Warp,
    whose contacts are dynamic."""
    timing: Throughput | None
    """Env steps per second; None when not measured (see `note`)."""
    reset_s: float | None = None
    """First call of the jitted, vmapped reset over the EPISODES states (compile + run), for this model; None for a
    variant, whose states are the as-built ones moved onto its model (`with_model`)."""
    note: str = ""


@dataclass
class MjxBenchResults:
    device: str
    steps: int
    repeats: int
    substeps: int
    ik_iterations: int
    solver_iterations: int
    linesearch_iterations: int
    rows: list[Row] = field(default_factory=list)


def device_name() -> str:
    """'CPU' or the GPU's name (e.g. 'NVIDIA H100 80GB HBM3'), as the ik and pointcloud suites name devices."""
    device = jax.devices()[0]
    return "CPU" if device.platform == "cpu" else device.device_kind


def bench_episodes(scene: Scene, count: int = EPISODES, seed: int = 0) -> list[Episode]:
    """`count` type-3 episodes (grasp the object's first part, move it left) at random placements of `scene`'s
    object."""
    xml = scene.object_xml
    chain = tuple(task_type(3).build_chain({"P1": scene.part_names[0]}, {"D1": "left"}))
    xy, quat = random_placements(count, seed)
    return [Episode(obj_class=xml.parent.parent.name, obj_id=xml.parent.name, ep_id=i, task_type=3, split="train",
                    chain=chain, task_instruction="", skill_instructions=("", ""),
                    obj_pose=(*quat[i, 1:], quat[i, 0], *xy[i], 0.0), obj_scale=1.0) for i in range(count)]


def circling_actions(tcp_pose: np.ndarray, steps: int) -> jnp.ndarray:
    """(steps, B, 7) Euler actions: each TCP target circles CIRCLE_RADIUS around the observed `tcp_pose` (B, 7) in
    the horizontal plane (its own phase), orientation held, gripper closed in the second half of each period."""
    hold = hold_action(tcp_pose)
    phase = np.linspace(0.0, 2 * np.pi, len(hold), endpoint=False)
    angle = 2 * np.pi * np.arange(steps)[:, None] / GRIPPER_PERIOD + phase
    actions = np.repeat(hold[None], steps, axis=0)
    actions[..., 0] += CIRCLE_RADIUS * np.cos(angle)
    actions[..., 1] += CIRCLE_RADIUS * np.sin(angle)
    closed = (np.arange(steps) % GRIPPER_PERIOD) >= GRIPPER_PERIOD // 2
    actions[..., 6] = np.where(closed[:, None], panda.FINGER_CLOSED, panda.FINGER_OPEN)
    return jnp.asarray(actions, jnp.float32)


def object_name(object_xml: Path) -> str:
    """The object's folder name, after its category where the name does not say it ('dispenser 103619')."""
    category, name = object_xml.parent.parent.name, object_xml.parent.name
    return name if name.startswith(category) else f"{category} {name}"


def object_scene(object_xml: Path) -> Scene:
    """The default scene with this object (for its part names and collision hulls)."""
    return build_scene(SceneConfig(object_xml=str(object_xml)))


def make_env(object_xml: Path, batch_size: int = 1):
    """A BraxPartInstructEnv (requires brax) of the object with its EPISODES bench episodes, settled on the CPU;
    `batch_size` sizes Warp's shared contact buffer."""
    from partinstruct_mjx.brax_env import BraxPartInstructEnv

    return BraxPartInstructEnv(object_xml, bench_episodes(object_scene(object_xml)), EnvConfig(backend="mjx"),
                               batch_size=batch_size)


def reset_states(env, count: int | None = None) -> tuple[object, float]:
    """`count` start states (default: one per episode; one jitted, vmapped reset, episodes drawn from the keys) and
    the wall seconds of that first call."""
    keys = jax.random.split(jax.random.PRNGKey(0), count or len(env.episodes))
    start = time.perf_counter()
    states = jax.jit(jax.vmap(env.reset))(keys)
    jax.block_until_ready(states)
    return states, time.perf_counter() - start


def cycled(states, batch_size: int):
    """`batch_size` states that cycle through the given ones (MJX's JAX implementation, whose data is all per
    environment; Warp's shared contact buffer cannot be indexed like this)."""
    index = jnp.arange(batch_size) % states.obs.shape[0]
    return jax.tree.map(lambda x: x[index], states)


def measure(env, states, steps: int, repeats: int) -> Throughput:
    """Env steps/s of `steps` jitted, vmapped env steps per call over the batch of `states`; JAX's caches are
    cleared first, so the compile time is the step's own."""
    batch_size = states.obs.shape[0]
    actions = circling_actions(np.asarray(states.obs[:, :7]), steps)
    step = jax.vmap(env.step)
    state = states

    @jax.jit
    def rollout(state, actions):
        return jax.lax.scan(lambda s, a: (step(s, a), None), state, actions)[0]

    def call():
        nonlocal state
        state = rollout(state, actions)
        return state.obs

    return measure_throughput(call, batch_size * steps, repeats, batch_size * steps)


def with_model(env, states, model: mujoco.MjModel):
    """Make `env` step `model` (a variant of its own) and move `states` onto it: fresh MJX data of `model` with the
    states' time, positions, velocities, activations, controls and warm start (the first substep recomputes the
    rest), so a variant costs no reset compile."""
    env.model = mjx.put_model(model)
    old = states.pipeline_state.data
    fresh = jax.tree.map(lambda x: jnp.broadcast_to(x, (old.qpos.shape[0], *x.shape)), mjx.make_data(env.model))
    data = fresh.replace(time=old.time, qpos=old.qpos, qvel=old.qvel, act=old.act, ctrl=old.ctrl,
                         qacc_warmstart=old.qacc_warmstart)
    return states.replace(pipeline_state=states.pipeline_state.replace(data=data))


def contact_slots(states) -> int:
    """MJX contact slots per environment of a batched state."""
    return int(states.pipeline_state.data._impl.contact.dist.shape[-1])


@contextlib.contextmanager
def _warp_default() -> Iterator[None]:
    """MJX's own switch for picking the Warp implementation by default on a CUDA GPU."""
    previous = os.environ.get("MJX_GPU_DEFAULT_WARP")
    os.environ["MJX_GPU_DEFAULT_WARP"] = "true"
    try:
        yield
    finally:
        if previous is None:
            del os.environ["MJX_GPU_DEFAULT_WARP"]
        else:
            os.environ["MJX_GPU_DEFAULT_WARP"] = previous


def measure_warp(object_xml: Path, batch_sizes: tuple[int, ...], steps: int, repeats: int) -> list[Row]:
    """The same env on MuJoCo Warp at each batch size when warp-lang is installed, or a row saying why not."""
    from mujoco.mjx import warp as mjx_warp

    name, hulls = object_name(object_xml), len(object_scene(object_xml).object_geoms)

    def unmeasured(note: str, batch: int = TARGET_BATCH) -> Row:
        return Row(name, AS_BUILT, "warp", batch, hulls, None, None, note=note)

    if not mjx_warp.WARP_INSTALLED:
        return [unmeasured("not installed (warp-lang, the `warp` module MuJoCo Warp needs, is not importable)")]
    rows = []
    with _warp_default():
        for batch in batch_sizes:
            try:
                env = make_env(object_xml, batch)
                if env.model.impl != mjx.Impl.WARP:
                    return [unmeasured(f"not measured: MJX picked impl '{env.model.impl.value}' on this device")]
                states, reset_s = reset_states(env, batch)
                rows.append(Row(name, AS_BUILT, "warp", batch, hulls, None, measure(env, states, steps, repeats),
                                reset_s))
            except Exception as err:  # a failed attempt is a result of this row: record it
                message = str(err).splitlines()[0] if str(err) else ""
                rows.append(unmeasured(f"failed: {type(err).__name__}: {message[:200]}", batch))
    return rows


def run(objects: list[Path], batch_sizes: tuple[int, ...] = DEFAULT_BATCH_SIZES, steps: int = 20,
        repeats: int = 5, on_row: Callable[[MjxBenchResults], None] | None = None,
        impls: tuple[str, ...] = IMPLS, variants: tuple[Variant, ...] = VARIANTS) -> MjxBenchResults:
    """Measure every object at every batch size on MJX's JAX implementation with, on the object with the most
    hulls, `variants` at TARGET_BATCH (or the largest batch size when it is not among them); then every object at
    every batch size on Warp. `impls` picks the implementations; `on_row` sees the results after each row."""
    config = EnvConfig(backend="mjx")
    results = MjxBenchResults(device_name(), steps, repeats, config.scene.substeps, config.ik.iterations,
                              config.scene.solver_iterations, config.scene.linesearch_iterations)
    hulls = {xml: len(object_scene(xml).object_geoms) for xml in objects}
    largest = max(objects, key=lambda xml: hulls[xml])
    budget_batch = TARGET_BATCH if TARGET_BATCH in batch_sizes else max(batch_sizes)

    def add(row: Row) -> None:
        results.rows.append(row)
        print(_row_line(row), flush=True)
        if on_row is not None:
            on_row(results)

    for xml in objects if "jax" in impls else ():
        env = make_env(xml)
        states, reset_s = reset_states(env)
        for batch in batch_sizes:
            add(Row(object_name(xml), AS_BUILT, "jax", batch, hulls[xml], contact_slots(states),
                    measure(env, cycled(states, batch), steps, repeats), reset_s))
        if xml != largest:
            continue
        for variant in variants:
            model = copy.deepcopy(env.scene.model)
            variant.edit(env.scene, model)
            moved = with_model(env, states, model)
            colliding = int(np.count_nonzero(model.geom_contype[env.scene.object_geoms]))
            add(Row(object_name(xml), variant.name, "jax", budget_batch, colliding, contact_slots(moved),
                    measure(env, cycled(moved, budget_batch), steps, repeats)))
    if "warp" in impls:
        for xml in objects:
            for row in measure_warp(xml, batch_sizes, steps, repeats):
                add(row)
    return results


def series_label(device: str, row: Row) -> str:
    """The plot's label of an as-built row's series."""
    return f"MJX ({row.impl}) on {device}, Panda + {row.object_name} ({row.hulls} hulls)"


def data_rows(results: MjxBenchResults) -> list[dict]:
    """Every row for the data file; the as-built rows form the plot's series, one per object and implementation."""
    rows = []
    for r in results.rows:
        t = r.timing
        series = series_label(results.device, r) if t is not None and r.variant == AS_BUILT else None
        rows.append(env_row(series, r.batch_size, t.per_s if t else None, t.spread if t else (None, None),
                            object=r.object_name, variant=r.variant, impl=r.impl, hulls=r.hulls,
                            contacts=r.contacts, compile_s=t.compile_s if t else None, reset_s=r.reset_s,
                            note=r.note))
    return rows


def _cells(r: Row) -> str:
    timing = r.timing.cells() if r.timing else f"{r.note} | - | -"
    reset = "-" if r.reset_s is None else f"{r.reset_s:.1f}"
    return f"{timing} | {reset}"


def _row_line(r: Row) -> str:
    reset = "" if r.reset_s is None else f", reset {r.reset_s:.1f} s"
    speed = f"{r.timing.per_s:>10,.0f} env steps/s, compile {r.timing.compile_s:.1f} s{reset}" if r.timing else r.note
    return f"{r.object_name:<10} {r.impl:<4} batch {r.batch_size:>6,}  {r.variant[:44]:<44} {speed}"


def target_line(results: MjxBenchResults) -> str:
    """The DESIGN.md target against the as-built rows at TARGET_BATCH, met or not, or why it is not assessed."""
    rows = [r for r in results.rows
            if r.variant == AS_BUILT and r.batch_size == TARGET_BATCH and r.timing]
    if not rows:
        return f"Target not assessed: batch {TARGET_BATCH:,} was not measured."
    parts = []
    for r in rows:
        compile_s = r.timing.compile_s + r.reset_s
        met = r.timing.per_s >= TARGET_STEPS_PER_S and compile_s < TARGET_COMPILE_S
        parts.append(f"`{r.object_name}` ({r.impl}) {r.timing.per_s:,.0f} env steps/s, compile {r.timing.compile_s:.1f} s "
                     f"(step) + {r.reset_s:.1f} s (reset): {'met' if met else 'not met'}")
    where = " (measured on a CPU, not the target's H100)" if results.device == "CPU" else ""
    return (f"Target (DESIGN.md: >= {TARGET_STEPS_PER_S:,} env steps/s at batch {TARGET_BATCH:,}, compile < "
            f"{TARGET_COMPILE_S:.0f} s, one H100){where}: " + "; ".join(parts) + ".")


def markdown(results: MjxBenchResults) -> str:
    """The per-object table, the collision-budget table (when measured) and the target line."""
    sweep = [r for r in results.rows if r.variant == AS_BUILT]
    budget = [r for r in results.rows if r.variant != AS_BUILT]
    text = (
        f"MJX on {results.device}: `BraxPartInstructEnv.step` vmapped over the batch and jitted, "
        f"{results.steps} env steps per call (`lax.scan`, the state carried from call to call). One env step = the batched JAX IK ({results.ik_iterations} "
        f"iterations) of a 7-D pose action, {results.substeps} MJX physics substeps of 5 ms, the SceneState "
        f"(finger contacts with forces), the progress of a type-3 skill chain (its predicates) and the observation. "
        f"{EPISODES} pre-settled episodes (random placements) repeat over the batch; each TCP target circles "
        f"{CIRCLE_RADIUS * 100:g} cm around the settled TCP and the gripper closes for {GRIPPER_PERIOD // 2} of every "
        f"{GRIPPER_PERIOD} steps. env steps/s: median over {results.repeats} repeats of one call (batch x steps "
        f"env steps), range = slowest - fastest repeat. Step compile = first call (trace, compile, run; JAX caches "
        f"cleared, no persistent cache) minus a warm call; reset = first call of the jitted, vmapped reset over the "
        f"{EPISODES} episodes (compile + run; once per model, so the same for every batch size). Contact slots: the contacts MJX evaluates every substep, fixed by the "
        f"collision set. Warp (`impl=\"warp\"`, MuJoCo Warp through MJX): contacts are found per step into a "
        f"buffer shared by the batch, so a batch is reset as a whole (one reset per batch size, its episodes drawn "
        f"from the keys) and its reset time is per batch size; the first Warp row's times include building Warp's "
        f"CUDA kernels unless Warp's own kernel cache already holds them.\n\n"
        "| object | impl | hulls | contact slots | batch | env steps/s (median) | range over repeats | step compile s "
        "| reset s |\n|---|---|---|---|---|---|---|---|---|\n"
        + "".join(f"| {r.object_name} | {r.impl} | {r.hulls} | {'-' if r.contacts is None else r.contacts} | "
                  f"{r.batch_size:,} | {_cells(r)} |\n" for r in sweep))
    if budget:
        reference = [r for r in sweep if r.impl == "jax" and r.object_name == budget[0].object_name
                     and r.batch_size == budget[0].batch_size]
        text += (
            f"\nCollision and solver budget, `{budget[0].object_name}` at batch {budget[0].batch_size:,}: each variant "
            f"changes only which geoms collide or the solver's iteration caps (the scene: {results.solver_iterations} "
            f"Newton, {results.linesearch_iterations} line-search iterations) in the compiled model and starts from "
            f"the as-built reset states (timing probes: with half of the hulls, or without the robot's contacts, the "
            f"object is not simulated faithfully; on the C backend a 4-iteration line search lost 5 of 36 successful "
            f"oracle rotations on 99 episodes of types 8, 11 and 15).\n\n"
            "| collision set | impl | colliding hulls | contact slots | env steps/s (median) | range over repeats "
            "| step compile s | reset s |\n|---|---|---|---|---|---|---|---|\n"
            + "".join(f"| {r.variant} | {r.impl} | {r.hulls} | {'-' if r.contacts is None else r.contacts} | "
                      f"{_cells(r)} |\n" for r in reference + budget))
    return text + "\n" + target_line(results) + "\n"
