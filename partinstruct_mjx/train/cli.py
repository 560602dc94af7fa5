"""`partinstruct train`: train a DP3 / DP3-S diffusion policy on the demos of `partinstruct demos`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Train a DP3-style diffusion policy on the demonstrations of a `partinstruct demos` run directory.

dp3 sees the static camera's point cloud (agentview_pcd, xyz); dp3s also sees which points belong to the current
target part (agentview_part_pcd, xyz + flag). Both see the proprioception (tcp_pose, joint_states, gripper_state)
and a WordLlama embedding of the instruction of the current step, and predict 16 actions by DDPM (100 noise levels,
squared-cosine schedule, epsilon prediction); acting uses 10 DDIM steps and executes 8 actions per prediction."""

EPILOG = """\
outputs in RUN:
  config.json         resolved settings, the data trained on, package versions, git commit
  normalizer.npz      action and proprioception ranges ([-1, 1] normalisation)
  instructions.npz    WordLlama vectors of every instruction seen (text -> 256-d vector)
  log.jsonl           training loss every --log-every steps, validation loss every --val-every steps
  checkpoints/<step>  orbax checkpoints: the latest and the best by validation loss

resume: run the same command again (Ctrl-C saves a checkpoint first); a RUN holding other settings is refused.
evaluate: partinstruct_mjx.train.policy.load_policy(RUN) gives the policy (its EMA weights, best checkpoint).

examples:
  partinstruct train --data demos/ --policy dp3s --out runs/dp3s
  partinstruct train --data demos/ --policy dp3 --out runs/small --steps 2000 --down-dims 64 128 256"""


def add_train_parser(subparsers) -> argparse.ArgumentParser:
    """Register the `train` subcommand on the main command's subparsers."""
    from partinstruct_mjx.train.config import INSTRUCTION_SOURCES, POLICIES, ModelConfig, TrainConfig

    train, model = TrainConfig("", "dp3", ""), ModelConfig()
    parser = subparsers.add_parser(
        "train", help="train a DP3 / DP3-S diffusion policy on demos (resumable)", description=DESCRIPTION,
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, metavar="DIR",
                        help="run directory of `partinstruct demos` (its data/*.hdf5 are read)")
    parser.add_argument("--policy", required=True, choices=list(POLICIES),
                        help="dp3 (agentview_pcd) or dp3s (agentview_part_pcd, with the target-part flag)")
    parser.add_argument("--out", type=Path, required=True, metavar="RUN", help="run directory to write or resume")
    parser.add_argument("--steps", type=int, default=train.steps, metavar="N",
                        help=f"optimiser steps (default {train.steps:,})")
    parser.add_argument("--batch-size", type=int, default=train.batch_size, metavar="B",
                        help=f"windows per step (default {train.batch_size})")
    parser.add_argument("--lr", type=float, default=train.lr, help=f"peak learning rate (default {train.lr:g})")
    parser.add_argument("--warmup-steps", type=int, default=train.warmup_steps, metavar="N",
                        help=f"linear warm-up before the cosine decay (default {train.warmup_steps}, at most a "
                             "tenth of --steps)")
    parser.add_argument("--weight-decay", type=float, default=train.weight_decay,
                        help=f"AdamW weight decay (default {train.weight_decay:g})")
    parser.add_argument("--no-ema", action="store_true", help="act with the raw weights, not their moving average")
    parser.add_argument("--val-ratio", type=float, default=train.val_ratio,
                        help=f"fraction of demos held out for the validation loss (default {train.val_ratio:g}; "
                             "at least one demo when there are two or more)")
    parser.add_argument("--val-every", type=int, default=train.val_every, metavar="N",
                        help=f"steps between validations and checkpoints (default {train.val_every})")
    parser.add_argument("--log-every", type=int, default=train.log_every, metavar="N",
                        help=f"steps between loss-log lines (default {train.log_every})")
    parser.add_argument("--instructions", choices=INSTRUCTION_SOURCES, default=train.instructions,
                        help="label each step with its skill's instruction (default, as evaluation in skill mode) "
                             "or the episode's task instruction")
    parser.add_argument("--seed", type=int, default=train.seed, metavar="S",
                        help="seed of the weights, validation split, batches and noise (default 0)")
    sizes = parser.add_argument_group("model size (defaults: DP3's)")
    sizes.add_argument("--down-dims", type=int, nargs="+", default=list(model.down_dims), metavar="C",
                       help=f"U-Net channels per level (default {' '.join(map(str, model.down_dims))})")
    sizes.add_argument("--encoder-dims", type=int, nargs="+", default=list(model.encoder_dims), metavar="C",
                       help=f"per-point MLP widths (default {' '.join(map(str, model.encoder_dims))})")
    sizes.add_argument("--feature-dim", type=int, default=model.feature_dim, metavar="C",
                       help=f"cloud, proprioception and instruction feature width (default {model.feature_dim})")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(func=run_train)
    return parser


def run_train(args: argparse.Namespace) -> int:
    """Train; project errors reach the main command, which exits 2."""
    from partinstruct_mjx.jax_setup import enable_compilation_cache
    from partinstruct_mjx.train.config import ModelConfig, TrainConfig
    from partinstruct_mjx.train.trainer import train

    config = TrainConfig(
        data=str(args.data), policy=args.policy, out=str(args.out), steps=args.steps, batch_size=args.batch_size,
        lr=args.lr, warmup_steps=args.warmup_steps, weight_decay=args.weight_decay, ema=not args.no_ema,
        val_ratio=args.val_ratio, val_every=args.val_every, log_every=args.log_every,
        instructions=args.instructions, seed=args.seed,
        model=ModelConfig(down_dims=tuple(args.down_dims), encoder_dims=tuple(args.encoder_dims),
                          feature_dim=args.feature_dim))
    enable_compilation_cache()
    try:
        summary = train(config, progress=not args.quiet)
    except KeyboardInterrupt:
        print(f"\ninterrupted: a checkpoint was saved in {args.out}; run the same command again to resume",
              file=sys.stderr)
        return 130
    if summary["resumed_from"] >= summary["steps"]:
        print(f"{args.out}: already trained for {summary['steps']} steps")
        return 0
    val = f", validation loss {summary['val_loss']:.4f}" if summary["val_loss"] is not None else ""
    print(f"{args.out}: trained steps {summary['resumed_from']}-{summary['steps']} on {summary['train_windows']} "
          f"windows; training loss {summary['train_loss']:.4f}{val}; best checkpoint at step {summary['best_step']}")
    return 0
