"""The `reconstruct` job: fetch the capture, resume the run directory from its last checkpoint,
call `core.pipeline.reconstruct` on the run the job stored at submit (`Job.resolved_run`, never
resolved again), evaluate the held-out views, publish the run directory.

A job's run directory lives in the worker's scratch folder (<scratch>/jobs/<id>/run). Every
checkpoint is also copied to the store (jobs/<id>/state/) and every finished frame published as
artifacts as soon as it is written, so that a worker on another machine (another scratch folder)
resumes where a lost one stopped.
"""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

from sqlalchemy import select

from core.config import ResolvedRun
from core.data import load_capture
from core.evaluation import evaluate_run
from core.pipeline import Stopped, reconstruct
from worker.execution import Host, JobStopped
from worker.models import Asset, Job
from worker.pipelines import MODEL_KIND, ReconstructParams
from worker.progress import JobLink

__all__ = ["ReconstructJob"]

# Share of a frame's progress taken by training; the rest is its renders and PLY.
TRAIN_SHARE = 0.97
# Share of the whole job left for publishing artifacts at the end.
PUBLISH_SHARE = 0.01
STAGES = {0: "starting", 1: "appearance", 2: "geometry", 3: "occlusion"}


class ReconstructJob:
    """One reconstruct job on this worker (see the module's docstring)."""

    retry_note = "retry resumes from the last checkpoint"

    def __init__(self, runner: Host, job: Job, params: ReconstructParams, link: JobLink):
        self.runner, self.job, self.params, self.link = runner, job, params, link
        self.blobs = runner.blobs
        self.part = job.parent_id is not None
        """A part of a parted job (docs/design.md 4.4): its group's frames only, published
        into the parent's artifacts; the parent's assembly evaluates and merges."""
        self.owner = job.parent_id or job.id
        """Whose artifacts the frames are."""
        self.frames = list(job.part_frames or [])

    def run(self) -> None:
        capture = self.runner.capture(self.job, self.link)
        run = self._run_dir()
        try:
            self._reconstruct(capture, run, self.resolved(capture))
        except Stopped as exc:
            raise JobStopped(exc.where) from exc
        if self.part:
            self._finish_part(run)
            return
        self.evaluate(run, capture)
        self.publish_final(run)

    def _run_dir(self) -> Path:
        """<scratch>/jobs/<id>/run, restored from jobs/<id>/state/ and the published frames
        when this machine does not have it (a job resumed elsewhere)."""
        job_id = self.job.id
        run = self.runner.settings.scratch / "jobs" / job_id / "run"
        if (run / "config.json").is_file():
            return run
        state = self.blobs.list(f"jobs/{job_id}/state")
        if state:
            self.link.log(f"restoring the run directory from the store ({len(state)} files)")
            self.runner.fetch(f"jobs/{job_id}/state", run)
            if not self.part:
                self.runner.fetch(f"jobs/{job_id}/artifacts/frames", run / "frames")
            for frame in self.frames:  # a part's own frames (the others are other parts')
                self.runner.fetch(f"jobs/{self.owner}/artifacts/frames/{frame}",
                                  run / "frames" / frame)
        return run

    def resolved(self, capture: Path) -> ResolvedRun:
        """The run this job stored at submit; a job stored before runs were (migration 0007)
        resolves its parameters here, once per attempt, as it always did."""
        if self.job.resolved_run is not None:
            return ResolvedRun.from_json(self.job.resolved_run, capture, where="resolved_run")
        return self.params.resolve(load_capture(capture),
                                   capture_name=self.job.capture_id or "capture")

    def _reconstruct(self, capture: Path, run: Path, resolved: ResolvedRun) -> None:
        link = self.link
        resume = (run / "config.json").is_file()
        if resume:
            link.log("resuming from the run directory's last checkpoint")
        run.parent.mkdir(parents=True, exist_ok=True)
        reconstruct(capture, run, resolved=resolved, resume=resume, progress=False,
                    model_files=self._model_files(run.parent, resolved.config.normal_estimator),
                    on_progress=self._on_progress(run), should_stop=link.should_stop,
                    gops=[self.job.part_index] if self.part else None)

    def _model_files(self, work: Path, name: str | None) -> dict[str, Path]:
        """Where the model the configuration names (`name`) is on this worker: an operator's
        allow-listed file, or the tenant's model asset fetched into the job's folder. A name
        that is neither fails the job (the API refuses it first; a path is never opened)."""
        if name is None:
            return {}
        allowed = self.runner.settings.normal_estimators
        if name in allowed:
            return {name: allowed[name]}
        with self.runner.store.session(write=False) as s:
            asset = s.scalar(select(Asset).where(Asset.id == name,
                                                 Asset.tenant == self.job.tenant))
        if asset is None or asset.kind != MODEL_KIND:
            raise ValueError(f"normal_estimator: {name!r} is neither a model asset of this "
                             "tenant nor a model this server offers")
        dest = work / "models" / asset.id / asset.filename
        if not dest.is_file():
            try:
                self.blobs.get_file(f"assets/{asset.id}/{asset.filename}", dest)
            except FileNotFoundError:
                raise ValueError(f"normal_estimator: asset {asset.id} is not in the store; "
                                 "upload the model again") from None
        return {name: dest}

    def _on_progress(self, run: Path):
        link = self.link
        last_logged = [-1]

        def on_progress(event) -> None:
            step_share = TRAIN_SHARE * event.step / max(event.iterations, 1)
            if event.kind == "frame_done":
                step_share = 1.0
            if self.part:  # a part counts its own frames
                event = replace(event, frame_index=self.frames.index(event.frame),
                                frames=len(self.frames))
            fraction = (event.frame_index + step_share) / event.frames * (1 - PUBLISH_SHARE)
            stage = ("outputs" if event.step >= event.iterations else event.phase
                     if event.phase != "key" else STAGES.get(event.stage, ""))
            link.update(fraction=fraction, stage=stage, frame=event.frame_index + 1,
                        frames=event.frames, iteration=event.step, iterations=event.iterations,
                        message=f"frame {event.frame} ({event.gaussians} Gaussians)",
                        milestone=event.kind in ("frame_start", "frame_done"))
            if event.kind == "frame_start":
                link.log(f"frame {event.frame} ({event.frame_index + 1}/{event.frames}) from "
                         f"step {event.step}")
                for note in event.notes:  # e.g. where its initial points came from
                    link.log(f"frame {event.frame}: {note}")
            elif event.kind == "step" and event.step // 100 != last_logged[0]:
                last_logged[0] = event.step // 100
                # The loss is read back every few steps only (core.pipeline.events), so a
                # resumed frame's first steps may have none yet.
                loss = "-" if event.loss is None else f"{event.loss:.4f}"
                link.log(f"frame {event.frame} step {event.step}/{event.iterations} stage "
                         f"{event.stage} loss {loss} gaussians {event.gaussians}")
            elif event.kind == "checkpoint":
                self._save_state(run, Path(event.path))
            elif event.kind == "frame_done":
                link.log(f"frame {event.frame} done")
                self.runner.publish(self.owner, run, frames=True if self.part else None)
                self._save_state(run, None)

        return on_progress

    def evaluate(self, run: Path, capture: Path) -> None:
        self.link.update(fraction=1 - PUBLISH_SHARE, stage="evaluating", message="")
        try:
            result = evaluate_run(run, capture, capture_name=self.job.capture_id or "capture")
        except ValueError as exc:  # e.g. no held-out camera: the job still succeeds
            self.link.log(f"evaluation skipped: {exc}")
            return
        psnr = result.get("psnr")
        self.link.log(f"held-out views: PSNR {psnr:.2f} dB" if psnr is not None else
                      "held-out views evaluated")

    def _save_state(self, run: Path, checkpoint: Path | None) -> None:
        """Copy what a resume needs (config, metrics, this checkpoint) to jobs/<id>/state/."""
        files = [run / "config.json", run / "metrics.json"]
        if checkpoint is not None:
            files.append(checkpoint)
        for path in files:
            if path.is_file():
                self.blobs.put_file(
                    f"jobs/{self.job.id}/state/{path.relative_to(run).as_posix()}", path)

    def publish_final(self, run: Path) -> None:
        """Publish what is new in the run directory, then drop the resume state: a finished
        job is never resumed."""
        self.link.update(fraction=1 - PUBLISH_SHARE / 2, stage="publishing", message="")
        published = self.runner.publish(self.job, run)
        self.link.log(f"published {published} artifacts")
        self.blobs.delete_prefix(f"jobs/{self.job.id}/state")
        shutil.rmtree(run.parent, ignore_errors=True)

    def _finish_part(self, run: Path) -> None:
        """A part's end: its frames are published (each when it finished); its records and
        the run's configuration go to jobs/<parent>/parts/<index>/ for the assembly, and its
        resume state is dropped."""
        self.link.update(fraction=1 - PUBLISH_SHARE / 2, stage="publishing", message="")
        published = self.runner.publish(self.owner, run, frames=True)
        for name in ("metrics.json", "config.json"):
            self.blobs.put_file(f"jobs/{self.owner}/parts/{self.job.part_index}/{name}",
                                run / name)
        self.link.log(f"published {published} artifacts; part {self.job.part_index} done")
        self.blobs.delete_prefix(f"jobs/{self.job.id}/state")
        shutil.rmtree(run.parent, ignore_errors=True)
