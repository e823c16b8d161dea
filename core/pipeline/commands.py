"""`dgs reconstruct CAPTURE --out RUN ...`. Bad input ends with one line on stderr and exit
status 2; no traceback."""

from __future__ import annotations

import argparse
import time

from core.cli import command_help, fail
from core.config import METHODS, PRESETS, SPLITS
from core.pipeline.run import reconstruct

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct", help=command_help("reconstruct"))
    p.add_argument("capture", help="capture folder (see `dgs capture validate`)")
    p.add_argument("--out", required=True, help="run directory (new or empty, or with --resume)")
    p.add_argument("--preset", default="fast", help="paper | fast | test (default fast)")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="slice of the capture's frame list (Python slice, default all)")
    p.add_argument("--gop", type=int, default=None,
                   help="frames per group of pictures: the first of each is a key frame, the "
                        "others are deformed from the frame before and refined (default: the "
                        "config's gop, 20)")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="JSON file overriding fields of the preset (the shape of "
                        "RUN/config.json's config)")
    p.add_argument("--downscale", type=float, default=None, metavar="F",
                   help="train and score on the images reduced by F (e.g. 4 for 1/4 resolution; "
                        "recorded in config.json)")
    p.add_argument("--split", default=None, choices=SPLITS,
                   help="held-out cameras: auto (the capture's test_cameras, else every 8th; "
                        "the default), capture, every8, or none (train on every camera; "
                        "metrics on training views)")
    p.add_argument("--method", default=None, choices=METHODS,
                   help="disentangled (the method, default) or 3dgs (a plain 3D Gaussian "
                        "Splatting, the baseline to compare with)")
    p.add_argument("--device", default=None, metavar="DEVICE",
                   help="auto | cpu | cuda | cuda:N: where to train (default: the config's "
                        "train.device, auto = CUDA when usable, else CPU; recorded in "
                        "config.json)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run in --out (finished frames are skipped)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_reconstruct)


def _reconstruct(args: argparse.Namespace) -> int:
    if args.preset not in PRESETS:
        return fail("reconstruct", f"--preset: expected one of {', '.join(PRESETS)}, "
                                    f"got {args.preset!r}")
    start = time.perf_counter()
    try:
        overrides: dict = {}
        if args.downscale is not None:
            overrides["downscale"] = args.downscale
        if args.split is not None:
            overrides["split"] = args.split
        if args.method is not None:
            overrides["train"] = {"method": args.method}
        metrics = reconstruct(args.capture, args.out, preset=args.preset, frames=args.frames,
                              config_file=args.config, resume=args.resume, gop=args.gop,
                              progress=not args.no_progress, device=args.device,
                              overrides=overrides or None)
    except ValueError as exc:  # CaptureError is a ValueError
        return fail("reconstruct", exc)
    n = len(metrics["frames"])
    print(f"reconstructed {n} frame(s) into {args.out} in {time.perf_counter() - start:.0f} s; "
          f"next: dgs eval {args.out}")
    return 0
