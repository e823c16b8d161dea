"""The last step of a reconstruction run as parts (docs/design.md 4.4): once every part has
succeeded, the worker that ran the last one (or, if it is lost, whichever worker a sweeper
sends the job to) rebuilds the run directory from the parts' published frames and records (jobs/<id>/artifacts/, jobs/<id>/parts/<index>/), merges
them (`core.pipeline.assemble`: metrics.json, sequence.json, plots), evaluates every frame
(eval.json, contact sheet) and publishes what is new. It runs under the parent's own lease, so a
worker lost while assembling is replaced like any other."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from core.pipeline.assemble import assemble
from worker.execution import Host
from worker.models import Job
from worker.pipelines import ReconstructParams
from worker.progress import JobLink
from worker.reconstruct_job import PUBLISH_SHARE, ReconstructJob

__all__ = ["AssembleJob"]


class AssembleJob:
    """The assembly of one parted reconstruct job on this worker."""

    retry_note = "retry assembles the parts again"

    def __init__(self, runner: Host, job: Job, params: ReconstructParams, link: JobLink):
        self.runner, self.job, self.link = runner, job, link
        self.blobs = runner.blobs
        # Evaluation and the final publish are a whole job's.
        self.whole = ReconstructJob(runner, job, params, link)

    def run(self) -> None:
        capture = self.runner.capture(self.job, self.link)
        run = self.runner.settings.scratch / "jobs" / self.job.id / "run"
        shutil.rmtree(run, ignore_errors=True)  # what an assembler lost before left
        self.link.update(fraction=1 - 2 * PUBLISH_SHARE, stage="assembling",
                         frame=self.job.frames, frames=self.job.frames,
                         message=f"{self.job.parts} parts")
        records = self._fetch(run)
        metrics = assemble(run, records, capture)
        self.link.log(f"assembled {len(metrics['frames'])} frames from {len(records)} parts")
        self.whole.evaluate(run, capture)
        self.whole.publish_final(run)
        self.blobs.delete_prefix(f"jobs/{self.job.id}/parts")

    def _fetch(self, run: Path) -> list[dict]:
        """The published frames into `run`, the parts' records (in part order) and one
        config.json (every part wrote the same)."""
        self.runner.fetch(f"jobs/{self.job.id}/artifacts", run)
        # What was fetched is already published; the final publish sends only what is new.
        self.runner.mark_published(run)
        parts_dir = run.parent / "parts"
        self.runner.fetch(f"jobs/{self.job.id}/parts", parts_dir)
        records = []
        for index in range(self.job.parts):
            metrics = parts_dir / str(index) / "metrics.json"
            if not metrics.is_file():
                raise RuntimeError(f"part {index} left no records (jobs/{self.job.id}/parts/"
                                   f"{index}/metrics.json); retry runs the assembly again")
            records.append(json.loads(metrics.read_text()))
        shutil.copyfile(parts_dir / "0" / "config.json", run / "config.json")
        return records
