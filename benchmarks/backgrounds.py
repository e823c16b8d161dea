"""Held-out PSNR of finished runs in front of several backgrounds.

`dgs eval` composites the capture on the run's own background (black for `dgs synth` captures),
which hides a wrong coverage wherever the model drew that colour. This script renders each run's
held-out views again in front of black, grey and white and scores them against the capture
composited on the same colour (image * mask + bg * (1 - mask), masks being coverage): a model
whose alpha matches the masks scores alike on all three.

    python benchmarks/backgrounds.py CAPTURE RUN [RUN ...]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "grey": (0.5, 0.5, 0.5), "white": (1.0, 1.0, 1.0)}


def score(capture_dir: Path, run: Path) -> dict[str, float]:
    """Whole-image PSNR (dB) over the held-out views of the first frame, per background."""
    import torch

    from core.data import CaptureDataset, load_capture
    from core.model import GaussianModel
    from core.render import RenderCamera, render
    from core.config import read_run
    from core.stages import plan

    resolved = read_run(run, capture_dir)
    schedule = resolved.config.train.schedule
    p = plan(schedule.iterations - 1, schedule)
    capture = load_capture(capture_dir)
    frame = capture.frames[0]
    model = GaussianModel.load_ply(run / "frames" / frame / "gaussians.ply")
    held = list(resolved.views.split.scored)
    ds = CaptureDataset(capture, frames=[frame], cameras=held,
                        downscale=resolved.views.downscale)
    out = {}
    for name, colour in BACKGROUNDS.items():
        bg = torch.tensor(colour)
        mse = []
        for i in range(len(ds)):
            s = ds[i]
            with torch.no_grad():
                camera = RenderCamera.from_camera(s.camera, near=resolved.config.train.near)
                r = render(model, camera, sh_degree=p.sh_degree, beta=p.beta, background=bg,
                           eps2d=resolved.config.train.eps2d,
                           antialiased=resolved.config.train.antialiased)
            rgb = torch.floor(r.rgb.clamp(0, 1) * 255 + 0.5) / 255  # as the 8-bit renders
            target = s.image if s.mask is None else s.image * s.mask + bg * (1 - s.mask)
            mse.append(float((rgb - target).square().mean()))
        out[name] = -10 * math.log10(sum(mse) / len(mse))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("runs", type=Path, nargs="+")
    args = ap.parse_args()
    print("| run | " + " | ".join(f"PSNR image on {n} (dB)" for n in BACKGROUNDS) + " |")
    print("|---|" + "---|" * len(BACKGROUNDS))
    for run in args.runs:
        row = score(args.capture, run)
        print(f"| {run.name} | " + " | ".join(f"{row[n]:.2f}" for n in BACKGROUNDS) + " |",
              flush=True)


if __name__ == "__main__":
    main()
