"""A sequence reconstructed as parts (docs/design.md 4.4; which groups of pictures can run on
their own is `core.config.independent_groups`): the assembly that makes their run directories
one run. Every part writes its frames into the run's namespace (frames/, renders/,
meshes/) and keeps its frames' records; assembly merges those records into RUN/metrics.json,
writes RUN/sequence.json from them and draws the plots, exactly what the run would hold had
every group run one after another in one process."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from core.plots import plot_run
from core.rundir import RunDir
from core.sequence import GopPlan

__all__ = ["assemble"]


def assemble(run_dir: str | os.PathLike[str], parts: Iterable[dict],
             capture_dir: str | os.PathLike[str] | None = None) -> dict:
    """Merge the metrics.json of every part (`parts`, each {"frames": {frame: record}, ...})
    into RUN/metrics.json (frames in the run's order), write RUN/sequence.json and the plots;
    returns the metrics. RUN/config.json must be there (every part writes the same one;
    `capture_dir` upgrades one an older version wrote, `core.config.read_run`)."""
    run = RunDir(run_dir)
    resolved = run.read_run(capture_dir)
    cfg, chosen = resolved.config, list(resolved.frames)
    merged: dict[str, dict] = {}
    metrics: dict = {}
    for part in parts:
        merged.update(part.get("frames") or {})
        metrics.update({k: v for k, v in part.items() if k != "frames"})
    metrics["frames"] = {f: merged[f] for f in chosen if f in merged}
    plan = GopPlan(chosen, cfg.gop, cfg.sequence, cfg.train.schedule.iterations)
    run.write("metrics.json", metrics)
    run.write("sequence.json", plan.record(metrics["frames"]))
    if metrics["frames"]:
        plot_run(Path(run.root))
    return metrics
