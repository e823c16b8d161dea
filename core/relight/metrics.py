"""Relit held-out views of a run, scored against a synthetic capture's second-light ground truth
(`dgs eval`, docs/design.md 3.3 and section 5), and the relit pictures of the contact sheet.

A `dgs synth` capture records its two lights in gt/lights.json: `images` names the light the
capture was filmed under, `relight` the second one, whose renders are gt/relight/<frame>/<cam>.png
(straight sRGB with the capture's coverage mask, like the images). The run is relit under the
second light's map (gt/envmaps/<name>.exr) with the albedo divided by the capture light's SH9
irradiance, and compared as `dgs eval` compares the held-out renders: PSNR over the figure's
pixels and over the whole image, SSIM on the image composited on the run's background. The
baseline without the AO term (visibility 1 in the shading) is scored beside it.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from core.data import CaptureDataset
from core.data.images import read_image, write_png
from core.metrics import rgb_scores
from core.model import GaussianModel
from core.relight.envmap import load_envmap
from core.relight.output import to_uint8
from core.relight.run import RelightParams, compose, prepare, view_gbuffer

__all__ = ["SHEET_MAPS", "relight_ground_truth", "relit_heldout"]

# The contact sheet's three relit columns (core.relight.presets).
SHEET_MAPS = ("builtin:studio", "builtin:sunset", "builtin:neon")


def relight_ground_truth(capture_dir: Path) -> dict | None:
    """{"envmap", "capture_light", "images"} paths of a synthetic capture's second light, or None
    when the capture has no such ground truth."""
    path = Path(capture_dir) / "gt" / "lights.json"
    if not path.is_file():
        return None
    doc = json.loads(path.read_text())
    light = doc.get("lights", {}).get(doc.get("relight", ""), {})
    if "envmap" not in light or not (path.parent / "relight").is_dir():
        return None
    return {"envmap": path.parent / light["envmap"], "capture_light": path,
            "images": path.parent / "relight"}


def _reduce_straight(image: np.ndarray, coverage: np.ndarray, shape) -> np.ndarray:
    """Straight colour (H, W, 3) with its coverage (H, W) area-averaged to `shape` (h, w)."""
    h, w = shape
    if image.shape[:2] == (h, w):
        return image
    num = cv2.resize((image * coverage[..., None]).astype(np.float32), (w, h),
                     interpolation=cv2.INTER_AREA)
    den = cv2.resize(coverage.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    return num / np.maximum(den[..., None], 1e-6)


def _target(gt_png: Path, capture, frame: str, cam: str, sample, background) -> np.ndarray:
    """The ground-truth relit view at the run's resolution, composited like the capture."""
    image = read_image(gt_png)[..., :3]
    mask_path = capture.mask_path(frame, cam)
    full_mask = read_image(mask_path)[..., 0] if mask_path is not None else np.ones(
        image.shape[:2], np.float32)
    h, w = sample.image.shape[:2]
    image = _reduce_straight(image, full_mask, (h, w))
    if sample.mask is None:
        return image
    m = sample.mask.numpy()
    return image * m + background * (1 - m)


def relit_heldout(run: Path, capture_dir: Path, frame: str, cameras: list[str],
                  downscale: float, *, sheet_maps=SHEET_MAPS, capture_light="auto",
                  device="cpu") -> dict:
    """Relight the held-out `cameras` of one frame. Returns {"scores": [per view {camera, psnr,
    psnr_full, ssim, psnr_no_ao, ...}] (empty without ground truth), "pictures": {camera:
    {map: sRGB (H, W, 3)}} for `sheet_maps` (exposure matched to the capture's, `compose`) and, with ground truth, "relit (gt light)" and
    "gt relit"}, and writes RUN/renders/<frame>/<camera>_relit.png (under the ground-truth
    second light) when the capture has one. `capture_light` is what the albedo is divided by:
    "auto" for the ground truth's stage light (uniform without one), else as RelightParams.
    The model is rendered on `device` (a torch device)."""
    truth = relight_ground_truth(capture_dir)
    params = RelightParams(envmap=str(truth["envmap"]) if truth else sheet_maps[0],
                           cameras=",".join(cameras), frames=None,
                           capture_light=(str(truth["capture_light"]) if truth else None)
                           if capture_light == "auto" else capture_light)
    plan = prepare(run, params, capture_dir)
    model = GaussianModel.load_ply(run / "frames" / frame / "gaussians.ply", device=device)
    maps = {name: load_envmap(name, plan.capture.up).sh9 for name in sheet_maps}
    ds = CaptureDataset(plan.capture, frames=[frame], cameras=cameras, downscale=downscale)
    background = np.asarray(plan.settings.background, np.float32)
    scores, pictures = [], {}
    for i in range(len(ds)):
        sample = ds[i]
        cam = sample.camera
        g = view_gbuffer(model, cam, plan)
        pictures[cam.id] = {name: compose(g, plan, sh, match_exposure=True)[0]
                            for name, sh in maps.items()}
        if truth is None:
            continue
        relit, _ = compose(g, plan, plan.env_sh9)
        no_ao, _ = compose(g, plan, plan.env_sh9, ao=False)
        target = _target(truth["images"] / frame / f"{cam.id}.png", plan.capture, frame, cam.id,
                         sample, background)
        fg = (sample.mask.numpy()[..., 0] > 0.5 if sample.mask is not None
              else np.ones(target.shape[:2], bool))
        with_ao, without = rgb_scores(relit, target, fg), rgb_scores(no_ao, target, fg)
        scores.append({"camera": cam.id, **with_ao,
                       **{f"{k}_no_ao": v for k, v in without.items()}})
        write_png(run / "renders" / frame / f"{cam.id}_relit.png", to_uint8(relit))
        pictures[cam.id] = {"relit (gt light)": relit, "gt relit": target, **pictures[cam.id]}
    return {"scores": scores, "pictures": pictures}
