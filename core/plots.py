"""Training curves of a run: RUN/plots/loss.png, psnr.png, gaussians.png (one line per frame).

Drawn with matplotlib's Agg backend so that no display is needed (workers, CI).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt

__all__ = ["PLOTS", "plot_run"]

# file name -> (record key, y label, log scale)
PLOTS: dict[str, tuple[str, str, bool]] = {
    "loss.png": ("total", "total loss", True),
    "psnr.png": ("psnr", "training PSNR (dB)", False),
    "gaussians.png": ("gaussians", "Gaussians", False),
}


def _smooth(values: list[float], width: int) -> list[float]:
    # Each step trains on one random view, so raw curves are noisy; a running mean shows trends.
    out, acc = [], 0.0
    for i, v in enumerate(values):
        acc += v
        if i >= width:
            acc -= values[i - width]
        out.append(acc / min(i + 1, width))
    return out


def plot_run(run_dir: str | os.PathLike[str]) -> list[Path]:
    """Draw the plots from RUN/metrics.json's per-frame histories; returns the files written."""
    matplotlib.use("Agg", force=True)

    run = Path(run_dir)
    metrics_path = run / "metrics.json"
    if not metrics_path.is_file():
        raise ValueError(f"run_dir: {metrics_path} not found (is {run} a run directory?)")
    frames = json.loads(metrics_path.read_text()).get("frames", {})
    written = []
    (run / "plots").mkdir(parents=True, exist_ok=True)
    for name, (key, label, log) in PLOTS.items():
        fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
        for frame, m in sorted(frames.items()):
            rows = [r for r in m.get("history", []) if r.get(key) is not None]
            if not rows:
                continue
            ys = [float(r[key]) for r in rows]
            if key != "gaussians":
                ys = _smooth(ys, max(1, len(ys) // 50))
            ax.plot([r["step"] for r in rows], ys, label=f"frame {frame}", linewidth=1)
        ax.set_xlabel("iteration")
        ax.set_ylabel(label)
        if log:
            ax.set_yscale("log")
        if len(frames) > 1:
            ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        path = run / "plots" / name
        fig.savefig(path)
        plt.close(fig)
        written.append(path)
    return written
