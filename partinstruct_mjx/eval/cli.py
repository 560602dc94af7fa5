"""`partinstruct eval`: evaluate a trained policy (or the oracle) on the test splits and write the success tables."""

from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path

from partinstruct_mjx.eval.config import (DEFAULT_EPISODES_PER_SPLIT, MODES, ORACLE, PLANNERS, TEST_SPLITS,
                                          EvalError)

DESCRIPTION = (
    "Roll out a policy on episodes of the test splits and report success rates (± standard error) per split in the "
    "paper's table layout, with completion rates and per task type, skill, target part and category breakdowns. "
    "Episodes are generated from --seed exactly as `partinstruct episodes` does (or read from --metadata), spread "
    "over each split's task types and categories, and run a batch of one object's episodes at a time until each "
    "succeeds or reaches its step limit (250 env steps at 20 Hz; 400 for test4).")

EPILOG = """\
policies:
  --policy oracle       the scripted expert; it reads the privileged simulator state and ignores instructions.
                        It plans each batch first in a private copy of the env, retrying a failed grasp or touch
                        there (--oracle-tries), then acts in the env with the draws that worked (docs/oracle.md)
  --policy RUN_DIR      a training run, loaded with partinstruct_mjx.train.policy.load_policy(RUN_DIR)
  From Python, partinstruct_mjx.eval.evaluate(config, out_dir, policy=..., planner=...) takes any object with
  reset(env, state, key) and act(env, state, instructions, key) -> (B, 7) Euler actions (docs/evaluation.md).

instructions given to the policy:
  no planner, --mode skill  the current ground-truth skill instruction (the paper's "GT plan" setting)
  no planner, --mode task   the task instruction
  --planner oracle          the ground-truth skill instruction, refreshed every --planner-every steps

success (--mode): skill = the episode's ground-truth skill chain is completed in order (the original's evaluation,
spec 7); task = the task's goals hold.

output (DIR):
  results.json   every episode's outcome (split, category, object, ep_id, task type, success, completion, steps,
                 the skill it stopped at, per-skill success, target parts), the aggregates, the resolved config,
                 versions and git SHA; rewritten atomically after every batch ("complete": false until the end)
  results.md     the tables
  videos/<split>/<ep_id>_<category>_<object>_type<T>_<success|failure>.mp4   with --videos K: the first K episodes
                 of each split (needs OpenGL; headless: MUJOCO_GL=egl)

resume: re-running the same command skips the episodes results.json already holds (an interrupted run loses no
finished batch); a DIR made with other settings is refused. Same settings and seed give the same episodes.

Exit 0 when the evaluation completes; 2 on bad input (unknown split, missing run directory, bad values)."""


def add_eval_parser(subparsers) -> argparse.ArgumentParser:
    """Register the `eval` subcommand on the main command's subparsers."""
    from partinstruct_mjx.tasks.episodes import SPLITS

    parser = subparsers.add_parser(
        "eval", help="evaluate a policy (or the oracle) on the test splits: success per split, in the paper's table",
        description=textwrap.fill(DESCRIPTION, 100), epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", required=True, metavar="RUN|oracle",
                        help=f"a training run directory, or '{ORACLE}' for the scripted expert")
    parser.add_argument("--splits", nargs="+", default=list(TEST_SPLITS), metavar="SPLIT",
                        help=f"splits to evaluate, some of {', '.join(SPLITS)} (default: {' '.join(TEST_SPLITS)})")
    parser.add_argument("--mode", choices=MODES, default="skill",
                        help="success criterion: skill (ground-truth skill chain completed; default, the "
                             "original's) or task (the task's goals)")
    parser.add_argument("--episodes-per-split", type=int, default=None, metavar="N",
                        help=f"episodes per split (default {DEFAULT_EPISODES_PER_SPLIT}, 1,800 over the five test "
                             "splits; with --metadata: all of the file's)")
    parser.add_argument("--metadata", type=Path, default=None, metavar="FILE",
                        help="episode metadata JSON (ours or the original's) to evaluate instead of generated episodes")
    parser.add_argument("--categories", nargs="+", default=None, metavar="C", help="only these object categories")
    parser.add_argument("--batch-size", type=int, default=16, metavar="B",
                        help="episodes of one object simulated together (default 16)")
    parser.add_argument("--backend", choices=["mujoco", "mjx"], default="mujoco",
                        help="physics: mujoco (C MuJoCo on CPU threads, default) or mjx (for a GPU)")
    parser.add_argument("--planner", choices=PLANNERS, default=None,
                        help="high-level planner whose instructions the policy follows (default: none, the env's)")
    parser.add_argument("--planner-every", type=int, default=None, metavar="N",
                        help="consult the planner every N env steps (default 1)")
    parser.add_argument("--videos", type=int, default=0, metavar="K",
                        help="MP4s of the first K episodes of each split (default 0)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR",
                        help="results directory (created, or resumed)")
    parser.add_argument("--seed", type=int, default=0, metavar="S",
                        help="seed of the generated episodes and of the policy's random keys (default 0)")
    parser.add_argument("--max-steps", type=int, default=None, metavar="N",
                        help="cap every episode at N env steps (default: the split's limit); for quick checks")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="physics threads, shared out among the workers (default: all cores)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="objects rolled out at once, each in a thread with its own env and a fork of the policy "
                             "(default 2 on the mujoco backend, 1 on mjx; outcomes do not depend on it)")
    parser.add_argument("--processes", type=int, default=1, metavar="N",
                        help="objects rolled out at once in N worker processes instead of threads, each loading its "
                             "own policy (default 1: none); faster than threads on a many-core machine, where the "
                             "threads share one Python interpreter lock (outcomes do not depend on it)")
    parser.add_argument("--assets", type=Path, default=None, metavar="DIR",
                        help="assets root with catalog.json (default: the built-in library)")
    parser.add_argument("--oracle-tries", type=int, default=None, metavar="N",
                        help="--policy oracle: tries per grasp or touch in its look-ahead copy of the env (default "
                             "10, oracle/backtrack.py's SEGMENT_TRIES; 1: no look-ahead, the closed-loop oracle "
                             "alone)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(func=run_eval)
    return parser


def run_eval(args: argparse.Namespace) -> int:
    """Evaluate and print the tables; project errors reach the main command, which exits 2."""
    from partinstruct_mjx.eval.config import EvalConfig
    from partinstruct_mjx.eval.metrics import split_table, success_table
    from partinstruct_mjx.eval.runner import REPORT, RESULTS, evaluate
    from partinstruct_mjx.jax_setup import enable_compilation_cache

    if args.planner_every is not None and args.planner is None:
        raise EvalError("--planner-every needs --planner")
    episodes = args.episodes_per_split
    if episodes is None and args.metadata is None:
        episodes = DEFAULT_EPISODES_PER_SPLIT
    config = EvalConfig(
        policy=str(args.policy), splits=tuple(args.splits), mode=args.mode, episodes_per_split=episodes,
        batch_size=args.batch_size, backend=args.backend, planner=args.planner, planner_every=args.planner_every or 1,
        videos=args.videos, seed=args.seed, max_steps=args.max_steps,
        metadata=None if args.metadata is None else str(args.metadata),
        categories=tuple(args.categories) if args.categories else None,
        assets=None if args.assets is None else str(args.assets), num_threads=args.threads,
        oracle_tries=args.oracle_tries, workers=args.workers, processes=args.processes)
    enable_compilation_cache()
    try:
        results = evaluate(config, args.out, progress=not args.quiet)
    except KeyboardInterrupt:
        done = (f"finished batches are in {args.out / RESULTS}" if (args.out / RESULTS).exists()
                else "no batch had finished, nothing was written")
        print(f"\ninterrupted: {done}; run the same command again to resume", file=sys.stderr)
        return 130
    summary = results["summary"]
    splits = [s for s in config.splits if summary["per_split"][s]["episodes"]]
    run = results["run"]
    print(f"Success rate (%) ± standard error, {results['label']}:\n")
    print(success_table(summary, splits, results["label"]))
    print()
    print(split_table(summary, splits))
    print(f"\n{run['episodes_run']} episodes run in {run['wall_s']:.0f} s, {run['resumed_episodes']} resumed; "
          f"wrote {args.out / RESULTS} and {args.out / REPORT}")
    return 0


def add_compare_parser(subparsers) -> argparse.ArgumentParser:
    """Register the `compare` subcommand: two evaluation runs, episode by episode."""
    parser = subparsers.add_parser(
        "compare", help="compare two evaluation runs on the same episodes: gained, lost, exact McNemar p",
        description=textwrap.fill(
            "Compare two `partinstruct eval` runs (two policies, or two versions of one) on the episodes both ran "
            "(same --seed or --metadata): the successes of each, the episodes B gained and lost against A, and the "
            "two-sided exact McNemar p-value of that split (the chance of one at least as uneven if the two did "
            "equally well), overall, per split and per task type, then the changed episodes.", 100))
    parser.add_argument("a", type=Path, metavar="A", help="the first run's directory (or its results.json)")
    parser.add_argument("b", type=Path, metavar="B", help="the second run's directory (or its results.json)")
    parser.add_argument("--list", type=int, default=20, metavar="N",
                        help="changed episodes to list (default 20)")
    parser.add_argument("--json", type=Path, default=None, metavar="FILE", help="also write the comparison as JSON")
    parser.set_defaults(func=run_compare)
    return parser


def run_compare(args: argparse.Namespace) -> int:
    """Print the comparison; project errors reach the main command, which exits 2."""
    import json

    from partinstruct_mjx.atomic import atomic_write
    from partinstruct_mjx.eval.compare import compare, comparison_markdown, load_results

    a, b = load_results(args.a), load_results(args.b)
    comparison = compare(a, b)
    labels = [f"{path} ({run['label']}{'' if run['complete'] else ', run not complete'})"
              for path, run in ((args.a, a), (args.b, b))]
    print(comparison_markdown(comparison, *labels, args.list))
    if args.json is not None:
        with atomic_write(args.json) as file:
            json.dump(comparison, file, indent=1)
    return 0
