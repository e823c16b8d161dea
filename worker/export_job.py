"""The `export` job (POST /v1/exports): a succeeded reconstruction delivered as PLY, SPZ or the
relightable sequence stream (`core.export.run.export_run`, `dgs export`).

Its inputs are gathered like a render's (`worker.relight_job.RelightJob`: the source job's
published config.json and frame PLYs, its capture), plus the source's sequence.json, which names
the groups of pictures the stream is cut into. The output folder is published under export/:
export/stream.dgss (kind stream), export/spz/<frame>.spz (spz), export/ply/<frame>.ply (ply)
and export/export.json (export). Nothing is resumed: a retried export starts over.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from core.export.codec import StreamConfig
from core.export.run import export_run
from worker.execution import JobStopped
from worker.pipelines import ExportJobParams
from worker.relight_job import FETCH_SHARE, PUBLISH_SHARE, RelightJob

__all__ = ["ExportJob"]


class ExportJob(RelightJob):
    """One export job on this worker (see the module's docstring)."""

    retry_note = "retry exports it again"
    params: ExportJobParams

    def run(self) -> None:
        self.work = self.work.with_name(self.work.name.replace("relight-", "export-"))
        try:
            self.link.update(fraction=0.0, stage="fetching inputs", message="")
            source = self._source()
            capture = self.runner.capture(self.job, self.link)
            run = self._run_dir(source, capture)
            self._sequence(source, run)
            p = self.params
            config = StreamConfig() if p.position_tolerance is None else StreamConfig(
                position=p.position_tolerance)
            out = self.work / "export"
            self.link.log(f"exporting {len(self.frames)} frame(s) of job {source.id} as "
                          f"{', '.join(p.formats)}")
            record = export_run(run, out, formats=p.formats, fps=p.fps, config=config,
                                capture_dir=capture, on_progress=self._on_export,
                                subject=p.subject, run_name=f"jobs/{source.id}")
            for fmt in ("spz", "stream"):
                if fmt in record:
                    r = record[fmt]
                    self.link.log(f"{fmt}: {r['bytes_per_frame'] / 1e3:.1f} kB a frame, "
                                  f"{r['ratio_to_ply']:.1f}x smaller than PLY")
            self.link.update(fraction=1 - PUBLISH_SHARE / 2, stage="publishing", message="")
            self.link.log(f"published {self.runner.publish(self.job, out, 'export/')} artifacts")
        finally:
            shutil.rmtree(self.work, ignore_errors=True)
            try:
                os.rmdir(self.work.parent)
            except OSError:
                pass

    def _sequence(self, source, run: Path) -> None:
        """The source's sequence.json, when it published one (a run of one frame has none)."""
        key = f"jobs/{source.id}/artifacts/sequence.json"
        if self.blobs.size(key) is not None:
            self._get(key, run / "sequence.json")

    def _on_export(self, what: str, done: int, total: int) -> None:
        if self.link.should_stop():
            raise JobStopped(f"{what} ({done} of {total})")
        share = 1 - FETCH_SHARE - PUBLISH_SHARE
        self.link.update(fraction=FETCH_SHARE + share * done / max(total, 1), stage="exporting",
                         iteration=done, iterations=total, message=what)
