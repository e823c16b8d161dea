"""The `relight` job (POST /v1/renders): relit renders of a succeeded reconstruction.

Inputs come from the store, not from the reconstruct worker's scratch folder: the source job's
published RUN/config.json and frames/<frame>/gaussians.ply (jobs/<source>/artifacts/...), its
capture (captures/<id>/, as for a reconstruction) and the envmap asset (assets/<id>/<file>).
They are gathered into a scratch run directory of this attempt and handed to
`core.relight.run.run_params`, whose output folder is published under relit/:
relit/<frame>/<camera>.png|.exr (kind relit), relit/<frame>.mp4 (an orbit's video) or, over
several frames, relit/videos/<camera>.mp4 (video), and relit/relight.json (relight). Nothing is resumed: a retried or re-delivered render starts over (views are cheap
next to a reconstruction).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from sqlalchemy import select

from core.config import parse_frames
from core.files import write_json
from core.relight.run import RelightParams, RelightStopped, run_params
from worker.execution import Host, JobStopped
from worker.models import Asset, Job
from worker.pipelines import RelightJobParams, makes_results
from worker.progress import JobLink

__all__ = ["RelightJob"]

# Shares of the job's progress: gathering the inputs, then the views, then publishing.
FETCH_SHARE = 0.02
PUBLISH_SHARE = 0.02


class RelightJob:
    """One relight job on this worker (see the module's docstring)."""

    retry_note = "retry renders it again"

    def __init__(self, runner: Host, job: Job, params: RelightJobParams, link: JobLink):
        self.runner, self.job, self.params, self.link = runner, job, params, link
        self.blobs = runner.blobs
        # Per attempt: a worker that lost its lease may still be cleaning up its own folder.
        self.work = runner.settings.scratch / "jobs" / job.id / f"relight-{link.owner.token}"
        self.frames: list[str] = []

    def run(self) -> None:
        try:
            self.link.update(fraction=0.0, stage="fetching inputs", message="")
            source = self._source()
            capture = self.runner.capture(self.job, self.link)
            run = self._run_dir(source, capture)
            params = self._core_params(self._envmap())
            out = self.work / "relit"
            self.link.log(f"relighting {len(self.frames)} frame(s) of job {source.id}")
            try:
                record = run_params(run, out, params, capture_dir=capture,
                                    on_progress=self._on_progress,
                                    should_stop=self.link.should_stop)
            except RelightStopped as exc:
                raise JobStopped(f"view {exc.done} of {exc.total}") from exc
            self._portable_record(out / "relight.json", source)
            self.link.log(f"relit {record['views']} view(s) of {len(record['frames'])} "
                          f"frame(s), {len(record['videos'])} video(s)")
            self.link.update(fraction=1 - PUBLISH_SHARE / 2, stage="publishing", message="")
            published = self.runner.publish(self.job, out, prefix="relit/")
            self.link.log(f"published {published} artifacts")
        finally:
            shutil.rmtree(self.work, ignore_errors=True)
            try:  # the job's folder, unless another attempt's is in it
                os.rmdir(self.work.parent)
            except OSError:
                pass

    # -- inputs -------------------------------------------------------------------------------
    def _source(self) -> Job:
        """The succeeded reconstruction this job renders."""
        job = self.job
        source = (self.runner.store.get(job.source_job_id, job.tenant)
                  if job.source_job_id is not None else None)
        if source is None:
            raise ValueError("job_id: the reconstruction this render needs was deleted; "
                             "request a render of another reconstruction")
        if not makes_results(source.pipeline) or source.state != "succeeded":
            raise ValueError(f"job_id: job {source.id} is a {source.state} {source.pipeline} "
                             "job, not a succeeded reconstruction")
        return source

    def _get(self, key: str, dest: Path) -> Path:
        """The blob `key` at `dest`: a link to the store's file when the store is local."""
        dest.parent.mkdir(parents=True, exist_ok=True)
        local = self.blobs.local_path(key)
        if local is not None:
            if not local.is_file():
                raise FileNotFoundError(f"artifact store: no blob {key!r}")
            dest.symlink_to(local)
        else:
            self.blobs.get_file(key, dest)
        return dest

    def _run_dir(self, source: Job, capture: Path) -> Path:
        """A run directory of the source's config.json and the selected frames' PLYs."""
        base = f"jobs/{source.id}/artifacts"
        published = {b.key[len(base) + 1:] for b in self.blobs.list(f"{base}/frames")}
        order = json.loads((capture / "capture.json").read_text()).get("frames", [])
        finished = [f for f in order if f"frames/{f}/gaussians.ply" in published]
        if not finished:
            raise ValueError(f"job_id: job {source.id} has no published frame "
                             "(frames/<frame>/gaussians.ply); was it deleted?")
        self.frames = parse_frames(self.params.frames, finished)
        run = self.work / "run"
        self.link.update(fraction=FETCH_SHARE / 2, stage="fetching inputs", frames=len(
            self.frames), message=f"{len(self.frames)} frame(s) of job {source.id}")
        try:
            self._get(f"{base}/config.json", run / "config.json")
            for frame in self.frames:
                rel = f"frames/{frame}/gaussians.ply"
                self._get(f"{base}/{rel}", run / rel)
        except FileNotFoundError as exc:
            raise ValueError(f"job_id: the results of job {source.id} are not all in the "
                             f"store ({exc}); was it deleted?") from None
        return run

    def _envmap(self) -> str | None:
        """The map to pass to core: a fetched asset's path, builtin:NAME, or None (black)."""
        asset_id = self.params.envmap_asset
        if asset_id is None:
            return self.params.envmap
        with self.runner.store.session(write=False) as s:
            asset = s.scalar(select(Asset).where(Asset.id == asset_id,
                                                 Asset.tenant == self.job.tenant))
        if asset is None or asset.kind != "envmap":
            raise ValueError(f"envmap: asset {asset_id} was deleted (or is not an "
                             "environment map); upload the map again and request a new render")
        try:
            return str(self._get(f"assets/{asset.id}/{asset.filename}",
                                 self.work / "envmap" / asset.filename))
        except FileNotFoundError:
            raise ValueError(f"envmap: asset {asset.id} is not in the store; upload the map "
                             "again") from None

    def _core_params(self, envmap: str | None):
        """core's RelightParams (its checks raise ValueError: the job fails as invalid_input).
        Frames are already selected: the run directory holds only those."""
        shared = self.params.model_dump(exclude={"envmap", "frames"})
        return RelightParams(**shared, envmap=envmap, frames=None)

    # -- progress and outputs -----------------------------------------------------------------
    def _on_progress(self, event) -> None:
        share = 1 - FETCH_SHARE - PUBLISH_SHARE
        fraction = FETCH_SHARE + share * event.done / max(event.total, 1)
        frame = self.frames.index(event.frame) + 1 if event.frame in self.frames else 0
        fields = {"stage": "relighting", "iteration": event.done, "iterations": event.total,
                  "frames": len(self.frames)}
        if frame:
            fields.update(frame=frame, message=f"frame {event.frame}: {event.done}/"
                                               f"{event.total} views")
        self.link.update(fraction=fraction, **fields)
        if event.kind == "video":  # an orbit's frame, or a camera over every frame
            what = f"frame {event.frame}" if event.frame else Path(event.path).name
            self.link.log(f"{what}: video written ({event.done}/{event.total} views)")

    def _portable_record(self, path: Path, source: Job) -> None:
        """relight.json names this worker's scratch paths; publish it with the ids the client
        knows instead (the source job, the envmap asset, the frames asked for)."""
        record = json.loads(path.read_text())
        record["run"] = f"jobs/{source.id}"
        record["params"].update(envmap=self.params.envmap, frames=self.params.frames)
        write_json(path, record)
