"""A sequence reconstructed as parts (docs/design.md 4.4): which groups of pictures can run on
their own (`part_groups`), and the assembly that makes their run directories one run
(`assemble`): every part writes its frames into the run's namespace (frames/, renders/,
meshes/) and keeps its frames' records; assembly merges those records into RUN/metrics.json,
writes RUN/sequence.json from them and draws the plots, exactly what the run would hold had
every group run one after another in one process."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import fields
from pathlib import Path

from core.config import RunConfig, load_config
from core.plots import plot_run
from core.rundir import RunDir
from core.sequence import GopPlan, segment

__all__ = ["assemble", "part_groups"]


def part_groups(frames: Sequence[str], cfg: RunConfig) -> list[list[str]] | None:
    """The frames of each independent group of pictures of a run of `frames` with `cfg`, in
    order (one frame each when `sequence.enabled` is off); None when the groups are not
    independent (`sequence.refine_scope` "run": a group spends what earlier groups saved, so
    it must wait for them)."""
    if cfg.sequence.enabled and cfg.sequence.refine_scope != "group":
        return None
    gop = cfg.gop if cfg.sequence.enabled else 1
    return [list(g.frames) for g in segment(frames, gop)]


def run_config(record: dict) -> RunConfig:
    """The configuration a RUN/config.json record describes."""
    return load_config(record["preset"], overrides={
        f.name: record[f.name] for f in fields(RunConfig) if f.name in record}, where="config")


def assemble(run_dir: str | os.PathLike[str], parts: Iterable[dict]) -> dict:
    """Merge the metrics.json of every part (`parts`, each {"frames": {frame: record}, ...})
    into RUN/metrics.json (frames in the run's order), write RUN/sequence.json and the plots;
    returns the metrics. RUN/config.json must be there (every part writes the same one)."""
    run = RunDir(run_dir)
    record = run.read_config()
    cfg = run_config(record)
    chosen = list(record["frames"])
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
