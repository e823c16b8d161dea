"""One frame of a reconstruction, from its fitter to its outputs: a key frame's `Trainer` or a
tracked frame's `FrameTracker`, normal priors, resume from the frame's checkpoint, training
with the run's callbacks, then the PLY, the held-out renders, the mesh and its
`FrameRecord`."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import torch

from core.config import FrameRole, ResolvedRun, RunConfig, Views
from core.pipeline.events import History, Hooks
from core.pipeline.outputs import mesh_frame, render_heldout, thin
from core.pipeline.record import FrameRecord
from core.pipeline.seeds import record_seeds, static_seeds
from core.priors import NormalEstimator, fill_priors
from core.progress import LogLines, TerminalBar
from core.rundir import RunDir
from core.sequence import TrackedInputs, save_frame, tracker_for
from core.training import Callback, CheckpointCallback, FrameFitter, Trainer

__all__ = ["FrameJob", "fit_frame"]


@dataclass
class FrameJob:
    """What fitting a frame needs from its run."""

    capture: object
    """The `core.data.Capture`."""
    run: RunDir
    resolved: ResolvedRun
    """What the run does (RUN/config.json)."""
    estimator: NormalEstimator | None
    display: str | None
    """'bar' (a terminal), 'lines' (a log) or None (quiet)."""

    @property
    def cfg(self) -> RunConfig:
        return self.resolved.config

    @property
    def views(self) -> Views:
        return self.resolved.views

    @property
    def first(self) -> str:
        """The run's first frame: its key frame's static-scene seeds are kept by later key
        frames (`core.seeding`)."""
        return self.resolved.frames[0]


def _callbacks(job: FrameJob, frame: str, label: str, history: History,
               hooks: Hooks) -> list[Callback]:
    saver = CheckpointCallback(job.run.checkpoints, job.cfg.checkpoint_every,
                               filename=f"{frame}.pt", extra=lambda: history.records,
                               on_saved=lambda path: hooks.emit("checkpoint", path=str(path)))
    hooks.saver = saver
    callbacks: list[Callback] = [history, saver]
    if job.display is not None:
        callbacks.append(TerminalBar(label) if job.display == "bar" else LogLines(label))
    return [*callbacks, hooks]  # hooks last: a stop sees the step's history and checkpoint


def _fitter(job: FrameJob, role: FrameRole, inputs: TrackedInputs | None,
            callbacks: list[Callback]) -> FrameFitter:
    cfg = job.cfg
    if inputs is None:
        # A group's key frame starts what its tracked frames inherit: it trains longer
        # (sequence.key_steps); a frame alone, or every frame a key frame, does not.
        grouped = cfg.sequence.enabled and role.size > 1
        train = cfg.train.stretched(cfg.sequence.key_steps) if grouped else cfg.train
        static = static_seeds(job, train) if role.frame != job.first else None
        return Trainer.from_capture(job.capture, role.frame, train, views=job.views,
                                    callbacks=callbacks, static=static)
    return tracker_for(job.capture, role.frame, job.run, inputs, cfg.train, cfg.sequence,
                       job.views, callbacks=callbacks)


def fit_frame(job: FrameJob, role: FrameRole, inputs: TrackedInputs | None, label: str,
              hooks: Hooks) -> FrameRecord:
    """Fit `role.frame` (resuming from its checkpoint), write its outputs, return its record."""
    start = time.perf_counter()
    history = History()
    fitter = _fitter(job, role, inputs, _callbacks(job, role.frame, label, history, hooks))
    rig = getattr(fitter, "rig", None)
    if rig is not None and getattr(fitter, "seed", None) is not None:
        record_seeds(job.run, role.frame, fitter, first=role.frame == job.first)
    # A plain 3DGS has no geometry branch: no prior term to give priors to.
    use_rig = job.cfg.rig_priors and job.cfg.train.method != "3dgs"
    priors = fill_priors(fitter.views, job.estimator, rig if use_rig else None)
    if rig is not None and "priors" in rig.seconds:
        fitter.notes.append(rig.note())
    if rig is not None:
        close = near_note(rig.nearest(), fitter.near)
        if close:
            fitter.notes.append(close)
    checkpoint = job.run.checkpoint(role.frame)
    resumed_at = 0
    if checkpoint.is_file():
        history.records = list(fitter.load_checkpoint(checkpoint) or [])
        resumed_at = fitter.step
    fitter.train()
    _wait(fitter)
    train_seconds = time.perf_counter() - start
    tracked = inputs is not None
    mesh, extras, train_psnr = _outputs(job, role.frame, fitter, tracked)
    last = history.records[-1] if history.records else {}
    record = FrameRecord(
        iterations=fitter.iterations, renders=fitter.renders,
        seconds=round(time.perf_counter() - start, 3), train_seconds=round(train_seconds, 3),
        extras_seconds=extras, resumed_at=resumed_at,
        ao_bake_seconds=None if fitter.ao_seconds is None else round(fitter.ao_seconds, 3),
        gaussians=len(fitter.model), train_psnr=train_psnr,
        normal_prior=priors, stages="deform + refine" if tracked else "static (key frame)",
        gop=role.gop, position=role.position,
        next_track_id=fitter.group_next_id if tracked else len(fitter.model),
        final_losses={k: v for k, v in last.items()
                      if k not in ("step", "stage", "gaussians", "psnr", "seconds")},
        notes=fitter.notes, history=thin(history.records), mesh=mesh,
        seed_seconds=None if getattr(fitter, "seed_seconds", None) is None
        else round(fitter.seed_seconds, 3),
        rig_seconds={k: round(v, 3) for k, v in rig.seconds.items()} if rig is not None
        and rig.seconds else None)
    if tracked:
        record.previous, record.new_tracks = role.previous, fitter.state.born
        record.start = {"from": fitter.start, "scores": dict(fitter.race.scores),
                        "views": dict(fitter.race.views)}
        record.deform_loss, record.refine_steps = fitter.deform_loss, fitter.refine_steps
        record.refine_nominal, record.scoring_extra = (fitter.nominal_refine,
                                                       fitter.scoring_extra)
    return record


def near_note(nearest: float | None, near: float) -> str | None:
    """A warning when the rig's stereo found a surface nearer a training camera than twice the
    run's near plane: a subject that close is clipped in that camera's renders."""
    if nearest is None or nearest >= 2 * near:
        return None
    return (f"the rig's stereo found a surface {nearest:.3g} from a camera, within twice the "
            f"near plane ({near:.3g}); renders clip nothing nearer than the plane, so if the "
            f"subject comes that close set train.near below {nearest / 2:.3g}")


def _wait(fitter: FrameFitter) -> None:
    """Let the device finish the fitting's queued work, so that its time is the fitting's."""
    if fitter.device.type == "cuda":
        torch.cuda.synchronize(fitter.device)


def _outputs(job: FrameJob, frame: str, fitter: FrameFitter, tracked: bool
             ) -> tuple[dict | None, dict[str, float], float]:
    """The frame's outputs after its fitting, each timed: its PLY, held-out renders, mesh and
    the training views' PSNR. Returns (mesh statistics, {output: seconds}, that PSNR)."""
    seconds: dict = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[name] = round(now - clock, 3)
        clock = now

    save_frame(job.run.ply(frame), fitter.model, fitter.ids if tracked else None)
    lap("ply")
    render_heldout(job.capture, frame, fitter, job.run, job.views)
    lap("renders")
    mesh = mesh_frame(job.run, job.capture, frame, job.cfg.mesh)
    lap("mesh")
    psnr = round(fitter.evaluate(), 4)
    lap("evaluate")
    return mesh, seconds, psnr


def display_mode(progress: bool) -> str | None:
    """A bar on a terminal; elsewhere (a log, nohup) a line every 30 s, so long runs never go
    quiet."""
    return None if not progress else "bar" if sys.stderr.isatty() else "lines"
