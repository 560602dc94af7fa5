"""The `partinstruct` command line: simulate, bench."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

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

    bench = commands.add_parser(
        "bench", help="measure env steps/s of the CPU backend and write docs/benchmarks.md",
        description="Time the mujoco (C, CPU-thread) backend at several batch sizes; medians of repeated runs.")
    bench.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 2, 8, 32], help="default: 1 2 8 32")
    bench.add_argument("--steps", type=int, default=200, help="control steps per timed run (default 200)")
    bench.add_argument("--repeats", type=int, default=5, help="timed runs per batch size (default 5)")
    bench.add_argument("--threads", type=int, default=None, help="worker threads (default: all cores)")
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


def _random_placements(batch: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Object x/y in the original's workspace (spec 1.4) and a random yaw, as (w, x, y, z) quaternions."""
    rng = np.random.default_rng(seed)
    xy = np.column_stack([rng.uniform(-0.05, 0.08, batch), rng.uniform(-0.085, 0.2, batch)])
    yaw = rng.uniform(-np.pi, np.pi, batch)
    quat = np.column_stack([np.cos(yaw / 2), np.zeros(batch), np.zeros(batch), np.sin(yaw / 2)])
    return xy, quat


def _simulate(args) -> int:
    from partinstruct_mjx.control.scripted_pick import run_pick
    from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
    from partinstruct_mjx.sim.scene import SceneConfig, build_scene

    scene = build_scene(SceneConfig(object_xml=args.object))
    xy, quat = _random_placements(args.batch, args.seed)
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
    from partinstruct_mjx.bench import cpu_backend
    from partinstruct_mjx.bench.report import provenance_lines, write_section
    from partinstruct_mjx.provenance import provenance
    from partinstruct_mjx.sim.scene import build_scene

    scene = build_scene()
    results = []
    for batch in args.batch_sizes:
        result = cpu_backend.measure(scene, batch, args.steps, args.repeats, args.threads)
        results.append(result)
        print(f"batch {batch:>5}: {result.env_steps_per_s:>10,.0f} env steps/s  ({result.threads} threads)")
    command = " ".join(["partinstruct", "bench", *sys.argv[2:]]) if sys.argv[1:2] == ["bench"] else "partinstruct bench"
    body = "## CPU backend (C MuJoCo, thread pool)\n\n" + provenance_lines(provenance(), command) + "\n" + \
        cpu_backend.markdown(results, scene)
    if str(args.output) != "-":
        write_section(args.output, "cpu_backend", body)
        print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
