"""`dgs reconstruct CAPTURE --out RUN ...` and `dgs eval RUN [--capture CAPTURE]`.

Bad input ends with one line on stderr and exit status 2; no traceback.
"""

from __future__ import annotations

import argparse
import sys
import time

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct", help="reconstruct a capture into a run directory")
    p.add_argument("capture", help="capture folder (see `dgs capture validate`)")
    p.add_argument("--out", required=True, help="run directory (new or empty, or with --resume)")
    p.add_argument("--preset", default="fast", help="paper | fast | test (default fast)")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="slice of the capture's frame list (Python slice, default all)")
    p.add_argument("--gop", type=int, default=None,
                   help="frames per group of pictures (recorded; used once sequences land)")
    p.add_argument("--config", default=None, metavar="FILE",
                   help="JSON file overriding fields of the preset (shape of RUN/config.json)")
    p.add_argument("--downscale", type=float, default=None, metavar="F",
                   help="train and score on the images reduced by F (e.g. 4 for 1/4 resolution; "
                        "recorded in config.json)")
    p.add_argument("--device", default=None, metavar="DEVICE",
                   help="auto | cpu | cuda | cuda:N: where to train (default: the config's "
                        "train.device, auto = CUDA when usable, else CPU; recorded in "
                        "config.json)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run in --out (finished frames are skipped)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_reconstruct)

    e = sub.add_parser("eval", help="score a run's held-out views; writes RUN/eval.json")
    e.add_argument("run", help="run directory")
    e.add_argument("--capture", default=None, help="capture folder (default: the run's own)")
    e.add_argument("--device", default="auto", metavar="DEVICE",
                   help="auto | cpu | cuda | cuda:N: where the relit views are rendered "
                        "(default auto)")
    e.set_defaults(func=_eval)


def _fail(command: str, message: str) -> int:
    print(f"dgs {command}: {message}", file=sys.stderr)
    return 2


def _one_line(exc: Exception) -> str:
    from core.data.capture import CaptureError

    if isinstance(exc, CaptureError):
        shown = "; ".join(str(p) for p in exc.problems[:3])
        more = len(exc.problems) - 3
        return (f"not a valid capture: {shown}" + (f" (+{more} more)" if more > 0 else "")
                + " (see dgs capture validate)")
    return str(exc).replace("\n", " ")


def _reconstruct(args: argparse.Namespace) -> int:
    from core.config import PRESETS

    if args.preset not in PRESETS:
        return _fail("reconstruct", f"--preset: expected one of {', '.join(PRESETS)}, "
                                    f"got {args.preset!r}")
    from core.pipeline import reconstruct

    start = time.perf_counter()
    try:
        metrics = reconstruct(args.capture, args.out, preset=args.preset, frames=args.frames,
                              config_file=args.config, resume=args.resume, gop=args.gop,
                              progress=not args.no_progress, device=args.device,
                              overrides=None if args.downscale is None
                              else {"downscale": args.downscale})
    except ValueError as exc:  # CaptureError is a ValueError
        return _fail("reconstruct", _one_line(exc))
    n = len(metrics["frames"])
    print(f"reconstructed {n} frame(s) into {args.out} in {time.perf_counter() - start:.0f} s; "
          f"next: dgs eval {args.out}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    from core.evaluate import evaluate_run

    try:
        result = evaluate_run(args.run, args.capture, device=args.device)
    except ValueError as exc:
        return _fail("eval", _one_line(exc))
    cos = result["normal_cos"]
    normal = "n/a" if cos is None else f"{cos:.3f} ({result['normal_deg']:.1f} deg, vs " \
                                       f"{result['normal_reference']})"
    print(f"{args.run}: {result['views']} held-out view(s): PSNR {result['psnr']:.2f} dB, "
          f"SSIM {result['ssim']:.3f}, normal cosine {normal}")
    if result.get("relight"):
        r = result["relight"]
        print(f"  relit under the capture's second light: PSNR {r['psnr']:.2f} dB, SSIM "
              f"{r['ssim']:.3f} (without the AO term {r['psnr_no_ao']:.2f} dB)")
    if result.get("mesh"):
        m = result["mesh"]
        print(f"  mesh: Chamfer {100 * m['chamfer_relative']:.2f}% of the diagonal, normal "
              f"consistency {m['normal_consistency']:.3f}")
    print(f"  wrote {args.run}/eval.json and {args.run}/{result['contact_sheet']}")
    return 0
