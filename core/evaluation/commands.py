"""`dgs eval RUN [--capture CAPTURE]`: scores a run's held-out views into RUN/eval.json. Bad
input ends with one line on stderr and exit status 2; no traceback."""

from __future__ import annotations

import argparse

from core.cli import command_help, fail
from core.evaluation.run import evaluate_run

__all__ = ["register"]


def _db(psnr: float | None) -> str:
    """A PSNR for people; None when no held-out view had a foreground pixel."""
    return "n/a (no foreground)" if psnr is None else f"{psnr:.2f} dB"


def register(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser("eval", help=command_help("eval"))
    e.add_argument("run", help="run directory")
    e.add_argument("--capture", default=None, help="capture folder (default: the run's own)")
    e.add_argument("--device", default="auto", metavar="DEVICE",
                   help="auto | cpu | cuda | cuda:N: where the relit views are rendered "
                        "(default auto)")
    e.set_defaults(func=_eval)




def _eval(args: argparse.Namespace) -> int:
    try:
        result = evaluate_run(args.run, args.capture, device=args.device)
    except ValueError as exc:
        return fail("eval", exc)
    cos = result["normal_cos"]
    normal = "n/a" if cos is None else f"{cos:.3f} ({result['normal_deg']:.1f} deg, vs " \
                                       f"{result['normal_reference']})"
    lpips = "n/a" if result["lpips"] is None else f"{result['lpips']:.3f}"
    print(f"{args.run}: {result['views']} held-out view(s): PSNR {_db(result['psnr'])}, "
          f"SSIM {result['ssim']:.3f}, LPIPS {lpips}, normal cosine {normal}")
    if result.get("relight"):
        r = result["relight"]
        print(f"  relit under the capture's second light: PSNR {_db(r['psnr'])}, SSIM "
              f"{r['ssim']:.3f} (without the AO term {_db(r['psnr_no_ao'])})")
    if result.get("mesh"):
        m = result["mesh"]
        print(f"  mesh: Chamfer {100 * m['chamfer_relative']:.2f}% of the diagonal, normal "
              f"consistency {m['normal_consistency']:.3f}")
    print(f"  wrote {args.run}/eval.json and {args.run}/{result['contact_sheet']}")
    return 0
