"""What `core.pipeline.reconstruct` needs for sequences: a tracker for a frame of a capture, frame
PLYs with track ids, and RUN/sequence.json (DESIGN.md 3.3).

sequence.json is derived from metrics.json (which a resumed run, also on another machine, always
has), so it is rewritten whole after every frame: frames with their group, role, Gaussian count,
seconds, steps and how their deform stage went (rounds, start); the groups; totals.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from core.model import GaussianModel
from core.config import SequenceConfig
from core.sequence.frame import FrameTracker
from core.sequence.gop import roles_of, with_rekeys
from core.sequence.motion import align_tracks

__all__ = ["load_frame", "save_frame", "sequence_record", "tracker_from_capture"]


def save_frame(path: str | os.PathLike[str], model: GaussianModel,
               ids: torch.Tensor | np.ndarray | None = None) -> None:
    """The frame's PLY with its track ids (0..N-1 for a key frame: `ids` None), atomically."""
    from core.plyio import write_gaussian_ply

    path = Path(path)
    if ids is None:
        ids = np.arange(len(model))
    ids = ids.cpu().numpy() if isinstance(ids, torch.Tensor) else np.asarray(ids)
    tmp = path.with_name(path.name + ".tmp")
    write_gaussian_ply(tmp, {k: v.detach().cpu() for k, v in model.params.items()}, ids)
    os.replace(tmp, path)


def load_frame(path: str | os.PathLike[str]) -> tuple[GaussianModel, torch.Tensor]:
    """(model, track ids) of a frame PLY; a PLY without ids (a key frame written by another
    tool) gets 0..N-1."""
    from core.plyio import read_track_ids

    model = GaussianModel.load_ply(path)
    ids = read_track_ids(path)
    return model, torch.from_numpy(np.arange(len(model)) if ids is None else ids).long()


def tracker_from_capture(capture, frame: str, previous_ply: Path, next_id: int, train,
                         sequence: SequenceConfig, *, downscale: float = 1.0,
                         callbacks=(), ao_baker=None, reference_loss: float | None = None,
                         earlier_ply: Path | None = None, refine_credit: int = 0,
                         refine_reference: float | None = None,
                         earliest_ply: Path | None = None) -> FrameTracker:
    """A `FrameTracker` on the training cameras of `frame`, starting from the previous frame's
    PLY (`reference_loss`: that frame's `deform_loss`, for deform retries; `earlier_ply`:
    the frame before that in the same group, whose motion the deformation continues;
    `earliest_ply`: the one before that, for second-order predictions;
    `refine_credit`: refine steps it may run beyond the nominal, `core.sequence.budget.
    refine_credit`, which `SequenceConfig.refine_adapt` may spend; `refine_reference`: what
    a group's second frame compares its deform loss with, `core.sequence.budget.
    median_deform_loss`)."""
    from core.data.dataset import CaptureDataset
    from core.train import View, training_cameras

    if not Path(previous_ply).is_file():
        raise ValueError(f"previous frame: {previous_ply} not found; the frame before {frame!r} "
                         "in its group must be finished first")
    ids = [c.id for c in training_cameras(capture.cameras)]
    ds = CaptureDataset(capture, frames=[frame], cameras=ids, downscale=downscale)
    views = [View.from_sample(ds[i]) for i in range(len(ds))]
    model, track = load_frame(previous_ply)
    earlier = earliest = None
    if earlier_ply is not None and (sequence.motion_candidates or sequence.second_order):
        earlier = _aligned(earlier_ply, track, frame, "two")
        if earliest_ply is not None and sequence.second_order:
            earliest = _aligned(earliest_ply, track, frame, "three")
    return FrameTracker(views, model, track, next_id, train, sequence, callbacks=callbacks,
                        ao_baker=ao_baker, reference_loss=reference_loss, earlier=earlier,
                        refine_credit=refine_credit, refine_reference=refine_reference,
                        earliest=earliest)


def _aligned(ply: Path, track: torch.Tensor, frame: str, how_many: str):
    """`align_tracks` of the frame PLY `ply` to the track ids `track`."""
    if not Path(ply).is_file():
        raise ValueError(f"earlier frame: {ply} not found; the {how_many} frames before "
                         f"{frame!r} in its group must be finished first")
    before, before_ids = load_frame(ply)
    return align_tracks(track, before_ids, before.means.detach())


def _start_name(metrics: dict) -> str:
    """The kept start of a frame's metrics ("damping" in runs from before the second-order
    starts)."""
    start = metrics["start"]
    if "from" in start:
        return start["from"]
    return "rest" if not start["damping"] else f"damped {start['damping']:g}"


def sequence_record(chosen: list[str], gop: int, sequence: SequenceConfig,
                    frames: dict[str, dict]) -> dict:
    """The content of RUN/sequence.json from the run's per-frame metrics."""
    gop_eff = gop if sequence.enabled else 1
    # A frame re-keyed after losing track starts a group of its own.
    groups = with_rekeys(chosen, gop_eff, {f for f, m in frames.items() if m.get("rekeyed")})
    rows = []
    for r in roles_of(groups):
        m = frames.get(r.frame)
        rows.append({"frame": r.frame, "gop": r.gop, "position": r.position,
                     "role": "key" if r.key else "deformed", "previous": r.previous,
                     "done": m is not None,
                     "gaussians": None if m is None else m.get("gaussians"),
                     "seconds": None if m is None else m.get("seconds"),
                     "iterations": None if m is None else m.get("iterations"),
                     # Refine steps run (`refine_adapt` moves them off the nominal).
                     "refine_steps": None if m is None else m.get("refine_steps"),
                     "new_tracks": None if m is None else m.get("new_tracks"),
                     # How the deform stage went: rounds run (2+: a retry) and the start its
                     # kept round began from ("rest", "damped a", "second-order c").
                     "deform_rounds": None if m is None or not m.get("deform_rounds")
                     else len(m["deform_rounds"]),
                     "start": None if m is None or not m.get("start") else _start_name(m),
                     # Views the start race scored the kept start on (None: no race, or
                     # a run from before the race).
                     "start_views": None if m is None or not m.get("start")
                     else (m["start"].get("views") or {}).get(_start_name(m)),
                     # Tracking lost and the frame made a key frame: the end-loss ratio.
                     "rekeyed": None if m is None or not m.get("rekeyed")
                     else m["rekeyed"]["loss_ratio"]})
    done = [r for r in rows if r["done"]]

    def mean(role: str, key: str) -> float | None:
        vals = [r[key] for r in done if r["role"] == role and r[key] is not None]
        return round(float(np.mean(vals)), 3) if vals else None

    return {
        "version": 1, "gop": gop_eff, "method": "deform + refine" if sequence.enabled
        else "independent (every frame a key frame)",
        "frames": rows,
        "gops": [{"index": g.index, "key": g.key, "frames": list(g.frames)} for g in groups],
        "timings": {"seconds_total": round(sum(r["seconds"] or 0 for r in done), 3),
                    "seconds_per_key_frame": mean("key", "seconds"),
                    "seconds_per_deformed_frame": mean("deformed", "seconds")},
        "gaussians": {"mean": None if not done else round(float(np.mean(
            [r["gaussians"] for r in done])), 1),
                      "per_key_frame": mean("key", "gaussians"),
                      "per_deformed_frame": mean("deformed", "gaussians")},
    }
