"""The `partinstruct` command line: simulate, convert, episodes, demos, render, bench."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import sys
import time
from pathlib import Path


DEFAULT_BENCH_OUTPUT = Path("docs/benchmarks.md")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="partinstruct",
        description="PartInstruct on MuJoCo: part-level manipulation with batched rollouts.",
    )
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sim = commands.add_parser(
        "simulate", help="run a short scripted pick-and-lift episode on a batch of scenes and print a summary",
        description="Reset B scenes (random object placement and yaw from --seed), pick the object top-down with the "
                    "mink reference IK, lift it 15 cm, hold it 3 s, and print per-environment results.")
    sim.add_argument("--batch", type=int, default=4, help="number of environments stepped together (default 4)")
    sim.add_argument("--seed", type=int, default=0, help="seed of the object placements (default 0)")
    sim.add_argument("--object", type=str, default=None, help="object MJCF (default: the built-in test block)")
    sim.add_argument("--threads", type=int, default=None, help="worker threads (default: all cores)")
    sim.set_defaults(func=_simulate)

    _add_convert_parser(commands)
    from partinstruct_mjx.tasks.episodes_cli import add_episodes_parser

    add_episodes_parser(commands)
    from partinstruct_mjx.data.demos_cli import add_demos_parser

    add_demos_parser(commands)
    from partinstruct_mjx.obs.render_cli import add_render_parser

    add_render_parser(commands)
    from partinstruct_mjx.train.cli import add_train_parser

    add_train_parser(commands)
    from partinstruct_mjx.eval.cli import add_compare_parser, add_eval_parser
    from partinstruct_mjx.eval.config import ORACLE

    add_eval_parser(commands)
    add_compare_parser(commands)

    bench = commands.add_parser(
        "bench", help="measure speed (CPU backend, conversion) and write docs/benchmarks.md",
        description="cpu_backend: env steps/s of the mujoco (C, CPU-thread) backend at several batch sizes, medians of "
                    "repeated runs. convert: conversion seconds, hulls and vertices per object of --sources, with the "
                    "default (quality) CoACD settings and an empty cache. ik: batched JAX IK solves/s on the current "
                    "JAX device (compile time separate) and how many targets it and mink reach. pointcloud: JAX point "
                    "clouds/s on the current device (mug_000) and the OpenGL depth path for comparison. pybullet: our CPU env "
                    "vs PyBullet doing the same work the original's way, in one run. demos: successful oracle "
                    "demos/hour, episodes/s, env steps/s and the time split of `partinstruct demos` on --episodes "
                    "train episodes (one cold run for the compile overhead, then --repeats warm runs; default 1). eval: "
                    "episodes/minute of `partinstruct eval --policy oracle` (or --policy RUN) over the five test "
                    "splits with --episodes per split (cold and warm runs as demos), and the projected time of 1,800 "
                    "episodes. "
                    "mjx: MJX env steps/s of the jitted, vmapped BraxPartInstructEnv step (IK, physics, predicates) "
                    "on the current JAX device per --object and batch size, compile time separate, collision-budget "
                    "variants of the object with the most hulls, and impl='warp' when installed (needs brax).")
    bench.add_argument("suite", nargs="?", default="cpu_backend",
                       choices=["cpu_backend", "convert", "ik", "pointcloud", "pybullet", "demos", "eval", "mjx"],
                       help="what to measure (default cpu_backend)")
    bench.add_argument("--sources", type=Path, nargs="+", default=[Path("../shared/partnet_samples")],
                       help="convert suite: PartNet-Mobility folders (default ../shared/partnet_samples)")
    bench.add_argument("--batch-sizes", type=int, nargs="+", default=None,
                       help="default: 1 2 8 32 (cpu_backend), 1 64 1024 16384 (ik), 1 16 256 (pointcloud), 16 (demos, eval), "
                            "256 1024 4096 16384 (mjx)")
    bench.add_argument("--object", type=Path, action="append", default=None,
                       help="mjx suite: object MJCF, repeatable (default: the built-in mug_000)")
    bench.add_argument("--steps", type=int, default=None,
                       help="control steps per timed run (default 200; mjx: env steps per jitted call, default 20)")
    bench.add_argument("--repeats", type=int, default=None,
                       help="timed runs per batch size (default 5; 1 for demos and eval, whose runs take minutes; "
                            "eval: 0 times the cold run alone, as for the full evaluation)")
    bench.add_argument("--impls", nargs="+", choices=["jax", "warp"], default=["jax", "warp"],
                       help="mjx suite: MJX implementations to measure (default both; warp needs warp-lang and a "
                            "CUDA GPU). A run of one writes its own section of the output")
    bench.add_argument("--no-variants", action="store_true",
                       help="mjx suite: skip the collision- and solver-budget variants (each compiles for a minute)")
    bench.add_argument("--episodes", type=int, default=None,
                       help="demos suite: train episodes per run (default 256, 128 on each of two objects); eval "
                            "suite: episodes per test split (default 8)")
    bench.add_argument("--backend", choices=["mujoco", "mjx"], default="mujoco",
                       help="demos and eval suites: physics backend (default mujoco; mjx on a GPU)")
    bench.add_argument("--threads", type=int, default=None, help="worker threads/processes (default: all cores)")
    bench.add_argument("--oracle-tries", type=int, nargs="+", default=None, metavar="N",
                       help="demos and eval suites: the oracle's tries per grasp or touch to measure, side by side "
                            "(default: the default of `partinstruct demos` and `eval`, 10)")
    bench.add_argument("--oracle-restarts", type=int, nargs="+", default=None, metavar="N",
                       help="demos suite: times an episode whose tries all failed starts over, to measure side by "
                            "side (default: the default of `partinstruct demos`, 2)")
    bench.add_argument("--workers", type=int, nargs="+", default=None, metavar="N",
                       help="demos and eval suites: objects simulated at once (threads) to measure, side by side "
                            "(default: the default of `partinstruct demos` and `eval`, 2 on the mujoco backend)")
    bench.add_argument("--processes", type=int, nargs="+", default=None, metavar="N",
                       help="eval suite: worker processes (`partinstruct eval --processes`) to measure, side by side "
                            "with the --workers threads (default: none)")
    bench.add_argument("--policy", default=ORACLE, metavar="POLICY",
                       help="eval suite: 'oracle' (default) or a training run directory (`partinstruct train --out`); "
                            "a trained policy's section is kept apart from the oracle's")
    bench.add_argument("--output", type=Path, default=DEFAULT_BENCH_OUTPUT,
                       help=f"markdown file to update (default {DEFAULT_BENCH_OUTPUT}); '-' prints only")
    bench.set_defaults(func=_bench)

    args = parser.parse_args(argv)
    from partinstruct_mjx.errors import PartInstructError

    try:
        return args.func(args)
    except PartInstructError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


def _add_convert_parser(commands) -> None:
    from partinstruct_mjx.assets.convert import DEFAULT_CACHE_DIR, ConvertConfig
    from partinstruct_mjx.assets.decompose import DecompositionConfig
    from partinstruct_mjx.assets.mjcf import PhysicsConfig

    defaults, budget, physics = ConvertConfig(), DecompositionConfig(), PhysicsConfig()
    convert = commands.add_parser(
        "convert", help="convert PartNet-Mobility object folders (or a dataset tree) into MJCF assets",
        description="Convert PartNet-Mobility object folders into <out>/objects/<category>/<id>/ with CoACD convex "
                    "decomposition per part, part-labelled geoms, parts.npz surface points and meta.json, and update "
                    "<out>/catalog.json. Unchanged objects are skipped, decompositions are cached by content hash, "
                    "and a failed object leaves no folder behind.")
    convert.add_argument("sources", nargs="+", type=Path, help="object folders (with mobility.urdf) or trees of them")
    convert.add_argument("--out", type=Path, default=Path("assets_mjcf"), help="assets root (default ./assets_mjcf)")
    size = convert.add_mutually_exclusive_group()
    size.add_argument("--scale", type=float, default=None, help="multiply the dataset units by this (e.g. 0.1)")
    size.add_argument("--target-size", type=float, default=defaults.target_size,
                      help=f"scale each object so its largest extent is this many metres (default {defaults.target_size})")
    convert.add_argument("--rigid", action="store_true", help="freeze all joints (one rigid body per object)")
    mass = convert.add_mutually_exclusive_group()
    mass.add_argument("--mass", type=float, default=physics.mass, help=f"total mass in kg (default {physics.mass})")
    mass.add_argument("--density", type=float, default=None, help="density in kg/m^3 instead of a total mass")
    convert.add_argument("--max-hulls-per-part", type=int, default=budget.max_hulls_per_part,
                         help=f"default {budget.max_hulls_per_part}")
    convert.add_argument("--max-hulls-per-object", type=int, default=budget.max_hulls_per_object,
                         help=f"default {budget.max_hulls_per_object} (MJX cost grows with every hull)")
    convert.add_argument("--max-hull-vertices", type=int, default=budget.max_hull_vertices,
                         help=f"default {budget.max_hull_vertices}")
    convert.add_argument("--threshold", type=float, default=None,
                         help=f"CoACD concavity threshold (default {budget.threshold}; lower = finer)")
    convert.add_argument("--preset", choices=["quality", "balanced", "fast"], default="quality",
                         help="CoACD settings: quality (default, ~1 min per object), balanced (~2.7x faster), "
                              "fast (seconds; previews and tests)")
    convert.add_argument("--points-per-part", type=int, default=defaults.points_per_part,
                         help=f"surface points per part in parts.npz (default {defaults.points_per_part})")
    convert.add_argument("--seed", type=int, default=defaults.seed, help="seed of CoACD and the surface points")
    convert.add_argument("--workers", type=int, default=defaults.workers, help="decomposition processes (default: cores)")
    convert.add_argument("--timeout", type=float, default=defaults.timeout,
                         help=f"seconds allowed per part decomposition (default {defaults.timeout:g})")
    convert.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE_DIR, help=f"default {DEFAULT_CACHE_DIR}")
    convert.add_argument("--quiet", action="store_true", help="no progress bars")
    convert.set_defaults(func=_convert)


def _convert(args) -> int:
    import dataclasses

    from partinstruct_mjx.assets.convert import ConvertConfig, convert_objects, summary_table
    from partinstruct_mjx.assets.decompose import DecompositionConfig
    from partinstruct_mjx.assets.mjcf import PhysicsConfig

    decomposition = DecompositionConfig.preset(args.preset)
    decomposition = dataclasses.replace(
        decomposition, max_hulls_per_part=args.max_hulls_per_part, max_hulls_per_object=args.max_hulls_per_object,
        max_hull_vertices=args.max_hull_vertices, seed=args.seed,
        threshold=decomposition.threshold if args.threshold is None else args.threshold)
    config = ConvertConfig(
        scale=args.scale, target_size=None if args.scale is not None else args.target_size, rigid=args.rigid,
        physics=PhysicsConfig(mass=args.mass, density=args.density), decomposition=decomposition,
        points_per_part=args.points_per_part, seed=args.seed, workers=args.workers, timeout=args.timeout,
        cache_dir=str(args.cache_dir))
    records = convert_objects(args.sources, args.out, config, progress=not args.quiet)
    print(summary_table(records))
    return 1 if any(r.status == "failed" for r in records) else 0


def _simulate(args) -> int:
    from partinstruct_mjx.control.scripted_pick import run_pick
    from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
    from partinstruct_mjx.sim.scene import SceneConfig, build_scene, random_placements

    scene = build_scene(SceneConfig(object_xml=args.object))
    xy, quat = random_placements(args.batch, args.seed)
    start = time.perf_counter()
    with MujocoBackend(scene, args.batch, num_threads=args.threads) as backend:
        state = backend.reset(xy, quat)
        result = run_pick(backend, state)
    seconds = time.perf_counter() - start
    print(f"scene: Panda + {scene.object_xml} (parts: {', '.join(scene.part_names)})")
    print(f"{'env':>3}  {'object x, y':>14}  {'lift [m]':>8}  {'hold drift [mm]':>15}  {'grip [N]':>8}  result")
    for i in range(args.batch):
        print(f"{i:>3}  {xy[i, 0]:>6.3f}, {xy[i, 1]:>6.3f}  {result.lift[i]:>8.3f}  {result.hold_drift[i] * 1000:>15.1f}  "
              f"{result.grip_force[i]:>8.1f}  {'held' if result.success[i] else 'FAILED'}")
    print(f"{int(result.success.sum())}/{args.batch} objects lifted and held for 3 s; "
          f"{args.batch} environments simulated in {seconds:.1f} s (incl. reset, IK planning)")
    return 0 if result.success.all() else 1


def _bench(args) -> int:
    from partinstruct_mjx.bench.report import env_row, write_report
    from partinstruct_mjx.provenance import provenance

    command = " ".join(["partinstruct", "bench", *sys.argv[2:]]) if sys.argv[1:2] == ["bench"] else "partinstruct bench"
    if args.repeats is None:
        args.repeats = 1 if args.suite in ("demos", "eval") else 5
    least_repeats = 0 if args.suite == "eval" else 1  # eval: the cold run alone can be the measurement
    if args.repeats < least_repeats:
        print(f"error: --repeats {args.repeats}: the {args.suite} suite needs at least {least_repeats}",
              file=sys.stderr)
        return 2
    if args.steps is None:
        args.steps = 20 if args.suite == "mjx" else 200
    info, data = provenance(), None
    if args.suite == "convert":
        from partinstruct_mjx.assets.convert import ConvertConfig
        from partinstruct_mjx.bench import conversion

        config = ConvertConfig(workers=args.threads or ConvertConfig().workers)
        records, wall = conversion.measure(args.sources, config)
        for r in records:
            print(f"{r.object_id:<12} {r.category:<12} {r.status:<9} {r.seconds:>7.1f} s {r.hulls:>3} hulls "
                  f"{r.vertices:>4} vertices {r.reason}")
        title, heading, table = "convert", "Conversion (PartNet-Mobility samples)", conversion.markdown(records, wall, config)
    elif args.suite == "ik":
        from partinstruct_mjx.bench import ik
        from partinstruct_mjx.sim.scene import build_scene

        results = ik.run(build_scene(), batch_sizes=tuple(args.batch_sizes or (1, 64, 1024, 16384)))
        table = ik.markdown(results)
        print(table)
        title, heading = f"ik_{results.device.lower().replace(' ', '_')}", f"Inverse kinematics ({results.device})"
    elif args.suite == "pointcloud":
        from partinstruct_mjx import paths
        from partinstruct_mjx.bench import pointcloud
        from partinstruct_mjx.sim.scene import SceneConfig, build_scene

        scene = build_scene(SceneConfig(object_xml=str(paths.assets_root() / "objects/mug/mug_000/object.xml")))
        results = pointcloud.measure(scene, batch_sizes=tuple(args.batch_sizes or (1, 16, 256)))
        table = pointcloud.markdown(results)
        print(table)
        title, heading = f"pointcloud_{results.device.lower().replace(' ', '_')}", f"Point clouds ({results.device})"
    elif args.suite == "pybullet":
        from partinstruct_mjx import paths
        from partinstruct_mjx.bench import pybullet_baseline

        mug = paths.assets_root() / "objects/mug/mug_000/object.xml"
        baseline, ours = pybullet_baseline.compare(mug, [(1, 1), (8, 1), (32, 1), (8, 2)], args.steps, args.repeats)
        table = pybullet_baseline.markdown(baseline, ours, "mug_000", args.steps)
        print(table)
        title, heading = "pybullet", "CPU env vs PyBullet (the original's engine and method)"
        data = [env_row("PyBullet, the original's way (CPU, 1 thread)", 1, baseline.env_steps_per_s, baseline.spread,
                        engine="pybullet", threads=1)]
        data += [env_row(f"PartInstructEnv, mujoco backend (CPU, {threads} physics thread{'s' * (threads > 1)})",
                         batch, r.env_steps_per_s, r.spread, engine="partinstruct-mjx", threads=threads,
                         per_core_ratio=list(r.ratio))
                 for (batch, threads), r in ours.items()]
    elif args.suite in ("demos", "eval"):
        from partinstruct_mjx.workers import gpu_shared

        # Worker processes share the GPU: JAX in this process (from the device's name on) must not preallocate it.
        with gpu_shared() if args.suite == "eval" and args.processes else contextlib.nullcontext():
            title, heading, table = _bench_rollouts(args, info, command)
    elif args.suite == "mjx":
        title, heading, table, data = _bench_mjx(args, info, command)
    else:
        title, heading = "cpu_backend", "CPU backend (C MuJoCo, thread pool)"
        table, data = _bench_cpu_backend(args)
    if str(args.output) != "-":
        write_report(args.output, title, heading, table, info, command, data)
        print(f"wrote {args.output}")
    return 0


def _bench_rollouts(args, info: dict, command: str) -> tuple[str, str, str]:
    """Run the demos or eval suite, rewriting its section after every row; returns its title, heading and table."""
    import jax

    from partinstruct_mjx.bench.report import write_report
    from partinstruct_mjx.eval.config import ORACLE

    # Sections are keyed by what JAX ran on: the GPU, or the CPU and its cores (a GPU machine's 16 cores with
    # JAX_PLATFORMS=cpu are not this 2-core CPU).
    gpu = jax.default_backend() != "cpu"
    device = jax.devices()[0].device_kind if gpu else f"CPU, {os.cpu_count()} cores"
    title = f"{args.suite}_{device.lower().replace(' ', '_')}" if gpu else f"{args.suite}_cpu{os.cpu_count()}"
    name = "Demonstration synthesis" if args.suite == "demos" else "Evaluation"
    if args.suite == "eval" and args.policy != ORACLE:
        title, name = f"{title}_trained_policy", "Evaluation of a trained policy"
    heading = f"{name} ({device})"

    def write(partial_table: str) -> None:
        """Rewrite the section after every measured row, so a run stopped at a time limit keeps its rows."""
        if str(args.output) != "-":
            write_report(args.output, title, heading, partial_table, info, command)

    table = _bench_demos(args, write) if args.suite == "demos" else _bench_eval(args, write)
    return title, heading, table


def _bench_demos(args, on_table) -> str:
    """Run the demos suite; `on_table(markdown)` gets the table of the rows measured so far after each row."""
    import jax

    from partinstruct_mjx.bench import demos
    from partinstruct_mjx.jax_setup import enable_compilation_cache
    from partinstruct_mjx.oracle.backtrack import RESTARTS, SEGMENT_TRIES
    from partinstruct_mjx.workers import default_workers

    cache = enable_compilation_cache()
    episodes = demos.bench_episodes(args.episodes or demos.DEFAULT_EPISODES)
    device = f"{jax.default_backend()} ({jax.devices()[0].device_kind})"
    results = []
    for batch, tries, restarts, workers in itertools.product(args.batch_sizes or [16],
                                                             args.oracle_tries or [SEGMENT_TRIES],
                                                             args.oracle_restarts or [RESTARTS],
                                                             args.workers or [default_workers(args.backend)]):
        result = demos.measure(episodes, batch, args.repeats, args.threads, backend=args.backend, oracle_tries=tries,
                               workers=workers, oracle_restarts=restarts)
        results.append(result)
        print(f"batch {batch:>3}, oracle tries {tries}, restarts {restarts}, workers {workers}: "
              f"{result.demos_per_hour:>9,.0f} demos/hour, "
              f"{result.episodes_per_s:.2f} episodes/s, "
              f"{result.env_steps_per_s:,.0f} env steps/s, oracle success {result.successes}/{result.episodes}, "
              f"compile {result.compile_s:.1f} s")
        table = demos.markdown(results, episodes, device, f"on ({cache})")
        on_table(table)
    print(table)
    return table


def _bench_eval(args, on_table) -> str:
    """Run the eval suite; `on_table(markdown)` gets the table of the rows measured so far after each row."""
    import jax

    from partinstruct_mjx.bench import evaluation
    from partinstruct_mjx.jax_setup import enable_compilation_cache
    from partinstruct_mjx.oracle.backtrack import SEGMENT_TRIES
    from partinstruct_mjx.workers import default_workers

    cache = enable_compilation_cache()
    device = f"{jax.default_backend()} ({jax.devices()[0].device_kind})"
    results = []
    threads = args.workers or ([] if args.processes else [default_workers(args.backend)])
    parallel = [(workers, 1) for workers in threads] + [(None, processes) for processes in args.processes or []]
    for batch, tries, (workers, processes) in itertools.product(args.batch_sizes or [16],
                                                                args.oracle_tries or [SEGMENT_TRIES], parallel):
        config = evaluation.bench_config(args.episodes or 8, batch, args.backend, args.threads, tries, workers,
                                         processes, args.policy)
        tried = evaluation.oracle_tries(config)
        row = f"batch {batch:>3}, {f'oracle tries {tried}, ' if tried else ''}{evaluation.parallelism(config)}"
        result = evaluation.measure(config, args.repeats, on_run=lambda index, run: print(
            f"{row}, {'cold' if index == 0 else 'warm'} run: {run.episodes} episodes in {run.wall_s:.1f} s "
            f"({run.episodes / run.wall_s * 60:,.1f} episodes/min), {run.successes} successful", flush=True))
        results.append(result)
        print(f"{row}: {result.episodes_per_min:,.1f} episodes/min, success "
              f"{result.cold.successes}/{result.cold.episodes}, "
              f"{f'compile {result.compile_s:.1f} s, ' if result.warm else ''}"
              f"{evaluation.FULL_EVALUATION:,} episodes in {result.full_evaluation_min:,.1f} min")
        table = evaluation.markdown(results, device, f"on ({cache})")
        on_table(table)
    print(table)
    return table


def _bench_mjx(args, info: dict, command: str) -> tuple[str, str, str, list[dict]]:
    """Run the mjx suite, rewriting its section and data file after every row (an interrupted run keeps them)."""
    from partinstruct_mjx import paths
    from partinstruct_mjx.bench import mjx_env
    from partinstruct_mjx.bench.report import write_report

    device, impls = mjx_env.device_name(), tuple(args.impls)
    title = f"mjx_{device.lower().replace(' ', '_')}" + ("" if set(impls) == set(mjx_env.IMPLS) else f"_{impls[0]}")
    heading = f"MJX env steps (impl {', '.join(impls)}, {device})"

    def write(results):
        if str(args.output) != "-":
            write_report(args.output, title, heading, mjx_env.markdown(results), info, command,
                         mjx_env.data_rows(results))

    objects = args.object or [paths.assets_root() / "objects/mug/mug_000/object.xml"]
    results = mjx_env.run(objects, tuple(args.batch_sizes or mjx_env.DEFAULT_BATCH_SIZES), args.steps, args.repeats,
                          on_row=write, impls=impls, variants=() if args.no_variants else mjx_env.VARIANTS)
    table = mjx_env.markdown(results)
    print(table)
    return title, heading, table, mjx_env.data_rows(results)


def _bench_cpu_backend(args) -> tuple[str, list[dict]]:
    from partinstruct_mjx.bench import cpu_backend
    from partinstruct_mjx.bench.report import env_row
    from partinstruct_mjx.sim.scene import build_scene

    scene = build_scene()
    results = []
    for batch in args.batch_sizes or [1, 2, 8, 32]:
        result = cpu_backend.measure(scene, batch, args.steps, args.repeats, args.threads)
        results.append(result)
        print(f"batch {batch:>5}: {result.env_steps_per_s:>10,.0f} env steps/s  ({result.threads} threads)")
    rows = [env_row("mujoco backend (CPU threads): physics + state only, no IK or predicates", r.batch_size,
                    r.env_steps_per_s, r.spread, threads=r.threads) for r in results]
    return cpu_backend.markdown(results, scene), rows


if __name__ == "__main__":
    sys.exit(main())
