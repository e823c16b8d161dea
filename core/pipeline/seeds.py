"""A run's seeds beyond one frame: the static scene's seeds of the run's first key frame, which
later key frames keep (RUN/seeds/static.ply), and each key frame's seeds picture
(RUN/plots/seeds-<frame>.png)."""

from __future__ import annotations

import numpy as np

from core.config import TrainConfig
from core.data.points import PointCloud, read_points_ply, write_points_ply
from core.files import atomic_path
from core.rig.picture import seeds_picture
from core.rundir import RunDir
from core.seeding import seed_points

__all__ = ["record_seeds", "static_seeds"]


def _write_static(run: RunDir, cloud: PointCloud) -> None:
    with atomic_path(run.static_seeds()) as tmp:
        write_points_ply(tmp, cloud)


def record_seeds(run: RunDir, frame: str, trainer, first: bool) -> None:
    """After a key frame's `core.training.Trainer` seeded: its seeds picture over its first
    training view, and, for the run's first key frame of a scene with a subject, its static
    seeds (unless a resumed run wrote them already)."""
    seed = trainer.seed
    view = trainer.views[0]
    seeds_picture(run.plots / f"seeds-{frame}.png", view.camera, view.image.cpu().numpy(),
                  seed.parts, f"frame {frame}, camera {view.camera.id}")
    if first and seed.static is not None and not run.static_seeds().is_file():
        _write_static(run, seed.static)


def static_seeds(job, train: TrainConfig) -> PointCloud | None:
    """The static scene a later key frame keeps: RUN/seeds/static.ply, made from the run's first
    frame when this run has not (a part of a sequence job, docs/design.md 4.4: the same seeds
    as the whole run's, so the part's frames are the same); None for a capture whose masks do
    not mark a subject in a scene, or whose first frame has no subject."""
    from core.training.views import frame_views  # lazy: needs torch, as the trainer does

    if not job.views.subject:
        return None
    run = job.run
    if not run.static_seeds().is_file():
        views = frame_views(job.capture, job.first, job.views)
        subjects = [None if v.subject is None else v.subject.numpy() for v in views]
        if all(m is None for m in subjects):
            return None
        path = job.capture.points_path()
        points = read_points_ply(path) if path is not None and train.init.source in (
            "auto", "points") else None
        seed = seed_points([v.camera for v in views], [v.image.numpy() for v in views],
                           [None if v.mask is None else v.mask.numpy() for v in views],
                           train.init, n_random=train.init_points, seed=train.seed,
                           capture_points=points, max_gaussians=train.densify.max_gaussians,
                           subjects=subjects, clear_of=job.capture.cameras)
        _write_static(run, seed.static)
    cloud = read_points_ply(run.static_seeds())
    return PointCloud(cloud.points.astype(np.float64), cloud.colors)
