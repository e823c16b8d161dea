"""`dgs synth OUT [--frames F] [--views V] [--size W H] [--seed S] [--priors]
[--subject CHARACTER.glb [--fps F]]`."""

from __future__ import annotations

import argparse
import sys
import time

from core.cli import command_help
from core.synth.generate import SynthConfig, synthesize

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("synth", help=command_help("synth"))
    p.add_argument("out", help="new (or empty) output folder")
    p.add_argument("--frames", type=int, default=3, help="number of frames (default 3)")
    p.add_argument("--views", type=int, default=16, help="number of cameras (default 16)")
    p.add_argument(
        "--size", type=int, nargs=2, default=(128, 128), metavar=("W", "H"), help="image size"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--priors", action="store_true", help="also write degraded normal priors to normals/"
    )
    p.add_argument("--subject", default="", metavar="CHARACTER.glb",
                   help="film a skinned, animated glTF 2.0 character instead of the built-in "
                        "figure")
    p.add_argument("--fps", type=float, default=24.0,
                   help="frames per second of the character's animation (default 24)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    config = SynthConfig(
        frames=args.frames,
        views=args.views,
        width=args.size[0],
        height=args.size[1],
        seed=args.seed,
        priors=args.priors,
        subject=args.subject,
        fps=args.fps,
    )
    start = time.perf_counter()
    try:
        capture = synthesize(args.out, config)
    except ValueError as exc:
        print(f"dgs synth: {exc}", file=sys.stderr)
        return 2
    print(
        f"wrote {len(capture.cameras)} views x {len(capture.frames)} frames to {args.out} "
        f"in {time.perf_counter() - start:.1f}s"
    )
    return 0
