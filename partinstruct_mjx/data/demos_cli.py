"""`partinstruct demos`: synthesize oracle demonstrations into a resumable run directory, or replay stored ones."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from partinstruct_mjx.errors import DataError

DESCRIPTION = (
    "Run the scripted oracle on task episodes (batched, C MuJoCo on CPU threads by default) and store every "
    "successful episode as a demonstration with state and point-cloud observations: agentview_pcd (T, 1024, 3) and "
    "agentview_part_pcd (T, 1024, 4: xyz in the static camera's optical frame + target-part flag) from the JAX point "
    "renderer, tcp_pose, joint_states, gripper_state, object_pose, the 7-D absolute actions, the executing skill per "
    "step and the reset physics state. A failed grasp or touch and the skills after it are tried again from the "
    "simulator state before it (--oracle-tries), and an episode that every try failed starts over (--oracle-restarts); "
    "a demo keeps only the try that worked, so it is one real trajectory from the reset state. --episodes N spreads "
    "N episodes over every task type and category of the "
    "split (generated from --seed exactly as `partinstruct episodes` does); --metadata uses an existing file instead.")

EPILOG = """\
output (DIR):
  data/<category>.hdf5      robomimic layout: data/demo_k with actions, obs/*, skill_index, skill_instructions,
                            initial_state and the episode's attributes; data.attrs env_args
  metadata.json             the successful episodes, in the original's metadata schema
  episodes/<ep_id>.json     one sidecar per episode, failures included: outcome, failing skill, steps, skill
                            boundaries, reset state
  summary.json              counts, success rate and failing skills per task type, demos per category, provenance
  shards/, progress.json    per-batch files and the ledger that makes the run resumable
  selections/<digest>.json  the generated episodes of each --split/--episodes/--seed/--types/--categories asked for
                            (without --metadata), read back on resume instead of generating them again

resume: every batch is committed atomically. Re-running the same command skips episodes already committed
(successes and failures), so an interrupted run (Ctrl-C finalizes what was committed) continues where it stopped,
and a larger --episodes adds only the new episodes. A directory remembers its backend, seed, sampler,
--oracle-tries and --oracle-restarts and refuses different ones. The same episodes, --batch-size and --seed give
the same demos, however often the run was interrupted (an episode's demo depends neither on its scene nor on the
episodes beside it; another --batch-size can round the IK 1 ulp apart on some CPUs, and a grasp or push may amplify
that).

speed: each object category and batch size compiles the oracle and the env step once per process (seconds to tens
of seconds; JAX's persistent cache in ~/.cache/partinstruct_mjx/jax shortens later runs), so short runs are
dominated by compiling. Episodes run per object, streamed through --batch-size scenes (a scene whose episode ended
takes the next one) and committed every --batch-size finished episodes; the clouds of successful
episodes cost about as much as the simulation ('stride' sampling; 'fps', the original's, is several times slower).
`partinstruct bench demos` measures demos/hour on this machine.

export: --export-zarr DIR OUT writes DIR's demos (--categories: only those) to the zarr store OUT in 3D Diffusion
Policy's layout (data/point_cloud, data/part_point_cloud, data/state, data/action, ..., meta/episode_ends; zarr
format 2, as DP3 reads it), for training with DP3's own code; needs `pip install "partinstruct-mjx[zarr]"`.
docs/training.md lists every array.

replay: --replay DIR (or one of its .hdf5 files) re-simulates the stored demos in fresh envs from their episodes
and reports whether each reaches task success within its stored length (--skill-mode also checks skill-mode
success); exit 1 if any does not.

Exit 0 when the run completes, however many episodes the oracle failed (the summary says how many); exit 2 on bad
input (unknown split, type or category, a malformed metadata file, a directory started with other settings)."""


def add_demos_parser(subparsers) -> argparse.ArgumentParser:
    """Register the `demos` subcommand on the main command's subparsers."""
    from partinstruct_mjx.data.synthesis import ALL_TYPES, SAMPLERS, RENDER_CHUNK
    from partinstruct_mjx.tasks.episodes import SPLITS

    parser = subparsers.add_parser(
        "demos", help="synthesize oracle demonstrations (state + point clouds) into HDF5, resumable; or replay them",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, metavar="DIR", help="run directory to write or resume (required unless "
                        "--replay)")
    parser.add_argument("--split", default=None, metavar="SPLIT",
                        help=f"one of {', '.join(SPLITS)}, or {ALL_TYPES} (train for types 1-10 plus test4 for "
                             "11-16); default train, or every split of --metadata")
    parser.add_argument("--episodes", type=int, default=None, metavar="N",
                        help="number of episodes, spread over the split's task types and categories (default 100; "
                             "with --metadata: all of the file's)")
    parser.add_argument("--metadata", type=Path, default=None, metavar="FILE",
                        help="episode metadata JSON to use instead of generating episodes")
    parser.add_argument("--types", type=int, nargs="+", default=None, metavar="T", help="only these task types")
    parser.add_argument("--categories", nargs="+", default=None, metavar="C",
                        help="only these object categories (e.g. mug kitchen_pot)")
    parser.add_argument("--seed", type=int, default=0, metavar="N",
                        help="seed of the generated episodes and of the oracle (default 0)")
    parser.add_argument("--batch-size", type=int, default=16, metavar="B",
                        help="episodes of one object simulated together (default 16)")
    parser.add_argument("--sampler", choices=SAMPLERS, default="stride",
                        help="point-cloud sampling: stride (default, fast) or fps (farthest-point, the original's)")
    parser.add_argument("--backend", choices=["mujoco", "mjx"], default="mujoco",
                        help="physics: mujoco (C MuJoCo on CPU threads, default) or mjx")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="physics threads, shared among the workers (default: all cores)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="objects simulated at once, each in a thread with its own env: while one's physics runs "
                             "the other's oracle does (default: 2 on the mujoco backend, 1 on mjx); the demos do "
                             "not depend on it")
    parser.add_argument("--oracle-tries", type=int, default=None, metavar="N",
                        help="tries per grasp or touch: a failed one and what follows it is tried again from the "
                             "state before it with other random draws (default 10, oracle/backtrack.py's "
                             "SEGMENT_TRIES; 1: no backtracking)")
    parser.add_argument("--oracle-restarts", type=int, default=None, metavar="N",
                        help="times an episode whose tries all failed starts over from its reset state with fresh "
                             "draws (default 2, oracle/backtrack.py's RESTARTS; 0: never; none with --oracle-tries 1)")
    parser.add_argument("--assets", type=Path, default=None, metavar="DIR",
                        help="assets root with catalog.json (default: the built-in library)")
    parser.add_argument("--render-chunk", type=int, default=RENDER_CHUNK, metavar="N", help=argparse.SUPPRESS)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    replay = parser.add_argument_group("replay")
    replay.add_argument("--replay", type=Path, default=None, metavar="PATH",
                        help="replay the demos of a run directory or one of its HDF5 files instead of synthesizing")
    replay.add_argument("--skill-mode", action="store_true", help="with --replay: also check skill-mode success")
    replay.add_argument("--limit", type=int, default=None, metavar="N", help="with --replay: only the first N demos")
    export = parser.add_argument_group("export")
    export.add_argument("--export-zarr", nargs=2, type=Path, default=None, metavar=("DIR", "OUT"),
                        help="write the demos of run directory DIR to a new zarr store OUT (3D Diffusion Policy's "
                             "layout) instead of synthesizing")
    parser.set_defaults(func=run_demos)
    return parser


def run_demos(args: argparse.Namespace) -> int:
    """Synthesize (or replay); project errors reach the main command, which exits 2."""
    from partinstruct_mjx.jax_setup import enable_compilation_cache

    if args.export_zarr is not None:
        from partinstruct_mjx.data.zarr_export import export_zarr

        written = export_zarr(*args.export_zarr, categories=args.categories, progress=not args.quiet)
        print(f"{written['path']}: {written['demos']} demos, {written['steps']} steps")
        return 0
    enable_compilation_cache()
    if args.replay is not None:
        from partinstruct_mjx.data.replay import replay_demos, replay_table

        results = replay_demos(args.replay, batch_size=args.batch_size, skill_mode=args.skill_mode,
                               limit=args.limit, backend=args.backend, assets=args.assets, num_threads=args.threads)
        print(replay_table(results, args.skill_mode))
        ok = all(r.reproduced and (not args.skill_mode or r.skill_success_step is not None) for r in results)
        return 0 if ok else 1
    if args.out is None:
        raise DataError("--out DIR is required (the run directory to write or resume)")
    if args.batch_size < 1:
        raise DataError(f"--batch-size must be >= 1, got {args.batch_size}")
    from partinstruct_mjx.data.demos import check_env_args
    from partinstruct_mjx.data.synthesis import env_args, remembered_selection, select_episodes, synthesize

    if args.oracle_tries is not None and args.oracle_tries < 1:
        raise DataError(f"--oracle-tries must be >= 1, got {args.oracle_tries}")
    if args.oracle_restarts is not None and args.oracle_restarts < 0:
        raise DataError(f"--oracle-restarts must be >= 0, got {args.oracle_restarts}")
    if args.workers is not None and args.workers < 1:
        raise DataError(f"--workers must be >= 1, got {args.workers}")
    # before the selection is stored
    check_env_args(args.out, env_args(args.backend, args.sampler, args.seed, args.oracle_tries,
                                      args.oracle_restarts))
    if args.metadata is not None:
        episodes = select_episodes(args.split, args.episodes, args.seed, args.types, args.categories, args.metadata,
                                   args.assets)
    else:
        episodes = remembered_selection(args.out, args.split or "train",
                                        100 if args.episodes is None else args.episodes, args.seed, args.types,
                                        args.categories, args.assets)
    try:
        summary = synthesize(episodes, args.out, batch_size=args.batch_size, seed=args.seed, sampler=args.sampler,
                             backend=args.backend, progress=not args.quiet, assets=args.assets,
                             num_threads=args.threads, render_chunk=args.render_chunk, oracle_tries=args.oracle_tries,
                             oracle_restarts=args.oracle_restarts, workers=args.workers)
    except KeyboardInterrupt:
        print(f"\ninterrupted: committed batches are finalized in {args.out}; run the same command again to resume",
              file=sys.stderr)
        return 130
    print(report(summary, args.out))
    return 0


def report(summary: dict, out_dir: Path) -> str:
    """What this run did and what the directory holds, with the per-type success table."""
    run = summary["run"]
    timing = run["timing"]
    lines = [f"{out_dir}: {run['processed']} episodes run now ({run['successes']} demos), {run['already_done']} were "
             f"already done; the directory holds {summary['successes']} demos of {summary['episodes']} episodes"]
    if run["processed"]:
        lines.append(f"time {timing['wall_s']:.1f} s with {run['workers']} worker(s); summed over the threads: "
                     f"simulation+oracle {timing['rollout_s']:.1f} s, point clouds {timing['render_s']:.1f} s, "
                     f"writing {timing['write_s']:.1f} s, envs {timing['env_s']:.1f} s; "
                     f"{run['successes'] / timing['wall_s'] * 3600:,.0f} demos/hour including compilation")
    lines.append(f"{'type':>4}  {'episodes':>8}  {'demos':>5}  {'success':>7}  failing skills")
    for type_id, entry in summary["per_task_type"].items():
        failing = ", ".join(f"{name} {n}" for name, n in entry["failing_skills"].items()) or "-"
        lines.append(f"{type_id:>4}  {entry['episodes']:>8}  {entry['successes']:>5}  {entry['success_rate']:>7.0%}  "
                     f"{failing}")
    if summary["episodes"]:
        lines.append(f"{'all':>4}  {summary['episodes']:>8}  {summary['successes']:>5}  "
                     f"{summary['success_rate']:>7.0%}")
    return "\n".join(lines)
