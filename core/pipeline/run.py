"""`reconstruct`: every selected frame of a capture into a run directory (docs/design.md 2.3,
3.3). Every input is checked before anything is written; then, frame by frame in the order of
the group-of-pictures plan (`core.sequence.GopPlan`), a key frame gets the static stages and a
tracked frame is deformed from its predecessor and refined (`core.pipeline.frame.fit_frame`).
After each frame metrics.json and sequence.json are rewritten and its checkpoint dropped, so
an interrupted run resumes at the frame it was in, from that frame's last checkpoint. A run
carried from another machine (`core.pipeline.carry`, RUN/carried.json) keeps the frames
finished there, and its capture needs only the frames still to do."""

from __future__ import annotations

import os
from collections.abc import Callable, Collection
from dataclasses import replace
from pathlib import Path

from core.config import ResolvedRun, load_config, resolve_run
from core.data import check_capture
from core.device import check_device_spec, resolve_device
from core.pipeline.events import Hooks, Progress, Stopped
from core.pipeline.frame import FrameJob, display_mode, fit_frame
from core.plots import plot_run
from core.priors import load_estimator
from core.rundir import RunDir
from core.sequence import GopPlan

__all__ = ["reconstruct"]

SEQUENCE_NOTE = ("the first frame of each GoP is reconstructed with the full static stages, the "
                 "others deformed from the previous frame and refined (see sequence.json)")
INDEPENDENT_NOTE = ("sequence.enabled is off: every frame was reconstructed independently with the "
                    "full static stages")


def _on_run_device(resolved: ResolvedRun, device: str | None) -> ResolvedRun:
    """`resolved` with `device` (when given) and then the device it stands for written into
    train.device (`auto` becomes `cuda:0` or `cpu`), so that config.json says where the run
    trained; ValueError (before anything is written) when CUDA is asked for and not usable."""
    where = "device" if device is not None else "train.device"
    spec = check_device_spec(device, where) if device is not None else \
        resolved.config.train.device
    return resolved.on_device(str(resolve_device(spec, where)))


def _start(run: RunDir, resolved: ResolvedRun, capture_dir: Path, resume: bool) -> None:
    """Check the folder, and that a resumed run is the same run; then write config.json."""
    run.check_new_or_resumable(resume)
    if run.config.is_file() and not run.read_run(capture_dir).same_run(resolved):
        raise ValueError(f"resume: {run.config} records another configuration; resume with "
                         "the same --preset and --config")
    run.write("config.json", resolved.to_json())


def _resolve(capture, run: RunDir, resolved: ResolvedRun | None, preset: str,
             frames: str | None, config_file, overrides: dict | None,
             gop: int | None) -> ResolvedRun:
    """The run to do: `resolved` (a service's job), or the preset, `config_file`, `overrides`
    and `gop` resolved against the capture; a carried run's frames are those finished
    elsewhere, then the selected ones still to do."""
    if resolved is None:
        config = load_config(preset, config_file, overrides, gop=gop, where="config")
        resolved = resolve_run(capture, config, preset=preset, frames=frames)
    carried = run.read_carried()  # finished by another process (core.pipeline.carry)
    if carried:
        done = [f for f in run.read_run(capture.root).frames if f in carried]
        resolved = replace(resolved, frames=tuple(done + [f for f in resolved.frames
                                                          if f not in carried]))
    return resolved


def reconstruct(capture_dir: str | os.PathLike[str], run_dir: str | os.PathLike[str], *,
                preset: str = "fast", frames: str | None = None,
                config_file: str | os.PathLike[str] | None = None, resume: bool = False,
                gop: int | None = None, overrides: dict | None = None,
                progress: bool = True, on_progress: Callable[[Progress], None] | None = None,
                should_stop: Callable[[], bool] | None = None, device: str | None = None,
                model_files: dict[str, Path] | None = None,
                gops: Collection[int] | None = None,
                resolved: ResolvedRun | None = None) -> dict:
    """Reconstruct the selected frames (`frames`: 'A:B' over the capture's frame list) into
    `run_dir`; returns the metrics (also RUN/metrics.json). `resume` continues an interrupted
    run: finished frames are skipped, an unfinished one restarts from its checkpoint. The run
    is the preset, then `config_file`, then `overrides` (same shape), then `gop` (frames per
    group of pictures), resolved against the capture (`core.config.resolve_run`), unless
    `resolved` is the run already resolved (a service's job, resolved when it was submitted);
    config.json records it. `device` (auto, cpu, cuda, cuda:N) overrides train.device and
    config.json records the device it resolved to.

    `progress` shows a bar on a terminal; `on_progress` receives `Progress` events (every step,
    checkpoint and frame); `should_stop` is asked before each frame begins and after every
    step: when it returns True, `Stopped` is raised, after a step once the frame's checkpoint is
    written (a service's cooperative cancel; a time budget's stop at a frame boundary).
    `model_files` maps a model the configuration names (`normal_estimator`: a service's asset
    id or allow-listed name) to the file to load; config.json keeps the name. `gops` runs only
    those groups of pictures (a part of a sequence job, docs/design.md 4.4: with
    `sequence.refine_scope` "group" a group needs no other group's records);
    `core.pipeline.assemble` merges the parts' records."""
    if resolved is not None and (config_file is not None or overrides or gop is not None
                                 or frames is not None):
        raise ValueError("resolved: give a resolved run or frames, config_file, overrides and "
                         "gop, not both")
    capture_dir, run = Path(capture_dir), RunDir(run_dir)
    capture = check_capture(capture_dir)
    resolved = _on_run_device(_resolve(capture, run, resolved, preset, frames, config_file,
                                       overrides, gop), device)
    cfg, chosen = resolved.config, list(resolved.frames)
    named = cfg.normal_estimator
    estimator = load_estimator((model_files or {}).get(named, named), cfg.normal_estimator_space)
    _start(run, resolved, capture_dir, resume)
    carried = run.read_carried()
    metrics = run.read_metrics()
    metrics.update({"version": 1, "preset": resolved.preset, "gop": cfg.gop,
                    "note": SEQUENCE_NOTE if cfg.sequence.enabled else INDEPENDENT_NOTE})
    records = metrics.setdefault("frames", {})
    plan = GopPlan(chosen, cfg.gop, cfg.sequence, cfg.train.schedule.iterations)
    job = FrameJob(capture, run, resolved, estimator, display_mode(progress))
    for i, role in enumerate(plan.roles):
        if (gops is not None and role.gop not in gops) or (role.frame in records and (
                run.ply(role.frame).is_file() or role.frame in carried)):
            continue
        if should_stop is not None and should_stop():  # before the frame's setup and seeds
            raise Stopped(role.frame, None)
        hooks = Hooks(role.frame, i, len(chosen), on_progress, should_stop)
        label = f"frame {role.frame} ({i + 1}/{len(chosen)})"
        records[role.frame] = fit_frame(job, role, plan.inputs(i, records), label,
                                        hooks).to_json()
        run.write("metrics.json", metrics)
        run.write("sequence.json", plan.record(records))
        hooks.emit("frame_done", path=str(run.frame_dir(role.frame)))
        # The frame is finished (PLY and metrics on disk): its training state is not needed.
        run.checkpoint(role.frame).unlink(missing_ok=True)
    plot_run(run.root)
    return metrics
