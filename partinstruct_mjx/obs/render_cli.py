"""`partinstruct render`: an H.264 MP4 of a stored trajectory from the static camera (and the wrist camera)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_render_parser(subparsers) -> argparse.ArgumentParser:
    """Register the `render` subcommand on the main command's subparsers."""
    parser = subparsers.add_parser(
        "render", help="render a stored trajectory (.npz of qpos per step) to an MP4 video",
        description="Render every step of a trajectory file from the static 'agentview' camera (300 x 300, the "
                    "original's pose) to an H.264 MP4; with --wrist the hand-mounted wrist camera's view is placed "
                    "to its right. When the file names a target part per step, that part's visible pixels are "
                    "tinted green. The video is written atomically.",
        epilog="Trajectory files: an .npz with 'qpos' (T, nq), 'object_xml' (the object MJCF, relative to the "
               "assets root or absolute) and optionally 'part' (T,) target part names; written by "
               "partinstruct_mjx.obs.video.save_trajectory.")
    parser.add_argument("trajectory", type=Path, metavar="TRAJ.npz", help="trajectory file to render")
    parser.add_argument("--out", type=Path, default=None, metavar="VIDEO.mp4",
                        help="video to write (default: the trajectory's path with .mp4)")
    parser.add_argument("--wrist", action="store_true", help="add the wrist camera beside the static view")
    parser.add_argument("--fps", type=int, default=20, help="frames per second (default 20: one frame per 20 Hz "
                                                            "control step)")
    parser.set_defaults(func=run_render)
    return parser


def run_render(args: argparse.Namespace) -> int:
    """Render and report; SceneError (bad file, wrong qpos width) reaches the main command, which exits 2."""
    from partinstruct_mjx.obs.video import render_video

    out = args.out or args.trajectory.with_suffix(".mp4")
    frames = render_video(args.trajectory, out, wrist=args.wrist, fps=args.fps, progress=True)
    print(f"wrote {out}: {frames} frames at {args.fps} fps")
    return 0
