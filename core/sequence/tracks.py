"""Frames with track ids: a frame's PLY keeps each Gaussian's track id, so that a group's frames
stay in correspondence; and the tracker of a frame, built from the finished frames it starts
from (`core.sequence.plan.TrackedInputs`)."""

from __future__ import annotations

import os

import numpy as np
import torch

from core.config import SequenceConfig, TrainConfig, Views
from core.files import atomic_path
from core.model import GaussianModel
from core.plyio import read_gaussian_ply, read_track_ids, write_gaussian_ply
from core.rundir import RunDir
from core.sequence.motion import align_tracks
from core.sequence.plan import TrackedInputs
from core.render import RenderCamera
from core.sequence.hull import inside_hull
from core.sequence.tracker import FrameTracker
from core.training import frame_views

__all__ = ["frame_tracks", "load_frame", "save_frame", "tracker_for"]


def save_frame(path: str | os.PathLike[str], model: GaussianModel,
               ids: torch.Tensor | np.ndarray | None = None) -> None:
    """The frame's PLY with its track ids (0..N-1 for a key frame: `ids` None), atomically."""
    if ids is None:
        ids = np.arange(len(model))
    ids = ids.cpu().numpy() if isinstance(ids, torch.Tensor) else np.asarray(ids)
    with atomic_path(path) as tmp:
        write_gaussian_ply(tmp, {k: v.detach().cpu() for k, v in model.params.items()}, ids)


def load_frame(path: str | os.PathLike[str]) -> tuple[GaussianModel, torch.Tensor]:
    """(model, track ids) of a frame PLY; a PLY without ids (a key frame written by another
    tool) gets 0..N-1."""
    model = GaussianModel.load_ply(path)
    ids = read_track_ids(path)
    return model, torch.from_numpy(np.arange(len(model)) if ids is None else ids).long()


def tracker_for(capture, frame: str, run: RunDir, inputs: TrackedInputs, train: TrainConfig,
                sequence: SequenceConfig, views: Views, *, callbacks=(),
                ao_baker=None) -> FrameTracker:
    """A `FrameTracker` on the training views of `frame` (as the run's `views` select them),
    starting from the finished frames `inputs` names in `run`."""
    previous = run.ply(inputs.previous)
    if not previous.is_file():
        raise ValueError(f"previous frame: {inputs.previous} is not finished; the frame "
                         f"before {frame!r} in its group must be finished first")
    model, track = load_frame(previous)
    earlier = earliest = None
    if inputs.earlier is not None and (sequence.motion_candidates or sequence.second_order):
        earlier = _aligned(run, inputs.earlier, track)
        if inputs.earliest is not None and sequence.second_order:
            earliest = _aligned(run, inputs.earliest, track)
    seen = frame_views(capture, frame, views)
    moving = None
    if moves_subject(views, sequence):
        before = frame_views(capture, inputs.previous, views)
        moving = subject_rows(model.means, [seen, before], sequence)
    return FrameTracker(seen, model, track, inputs.next_id,
                        train, sequence, callbacks=callbacks, ao_baker=ao_baker,
                        reference_loss=inputs.reference_loss, earlier=earlier,
                        refine_credit=inputs.refine_credit,
                        refine_reference=inputs.refine_reference, earliest=earliest,
                        moving=moving)


def moves_subject(views: Views, sequence: SequenceConfig) -> bool:
    """Whether tracked frames move only the subject (`SequenceConfig.moving`; `auto`: where
    the run's masks mark a subject)."""
    if sequence.moving != "auto":
        return sequence.moving == "subject"
    return views.subject


def subject_rows(means: torch.Tensor, frames: list[list], sequence: SequenceConfig
                 ) -> torch.Tensor:
    """(N,) bool: `means` inside the subject hull (`core.sequence.hull`) of any of `frames`
    (each a list of `core.training.View`)."""
    inside = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    for views in frames:
        cams = [RenderCamera.from_camera(v.camera, device=means.device) for v in views]
        inside |= inside_hull(means, cams, [v.subject_mask for v in views],
                              dilate_pixels=sequence.hull_dilate, share=sequence.hull_share)
    return inside


def frame_tracks(run: RunDir, frame: str) -> tuple[np.ndarray, np.ndarray]:
    """(track ids (N,), positions (N, 3)) of a finished frame: from its PLY, or from the
    tracks a carried run brought (frames/<frame>/tracks.npz, `core.pipeline.carry`)."""
    ply = run.ply(frame)
    if ply.is_file():
        ids = read_track_ids(ply)
        means = read_gaussian_ply(ply)["means"]
        return (np.arange(len(means)) if ids is None else ids), means
    with np.load(run.frame_dir(frame) / "tracks.npz", allow_pickle=False) as z:
        return z["ids"], z["means"]


def _aligned(run: RunDir, frame: str, track: torch.Tensor):
    """`align_tracks` of finished `frame`'s Gaussians to the track ids `track`."""
    ids, means = frame_tracks(run, frame)
    return align_tracks(track, torch.from_numpy(ids).long(), torch.from_numpy(means).float())
