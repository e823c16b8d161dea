"""A masked real subject from an unmasked real capture (issue 23): key out what stands in front of
the scene's dominant plane.

The fox is a mounted head on a wall: the wall is one plane, the head and its plaque stand out of
it. From a model trained on the unmasked capture (a run's PLY or checkpoint):

1. the plane: RANSAC over the centres of the opaque Gaussians (the wall holds most of them),
   oriented towards the cameras;
2. the subject: Gaussians more than `--margin` (a fraction of the cameras' distance to their
   look-at centre) in front of it, reduced to the connected cluster (voxels of `--voxel` of
   that distance, 26-neighbours) nearest the look-at centre, so that picture frames, a mirror or
   a curtain elsewhere on the wall stay background;
3. per camera: those Gaussians' appearance coverage rendered on the ideal pinhole at
   `1/--render-scale` of the source size, mapped into the source's distorted pixels, kept where
   it exceeds 0.5, stray blobs cut off (`_clean`), holes filled, written 0/255.

The new capture hard-links the images (no copy) and adds `masks/`; `capture.json` is the
source's. The masks are derived, not drawn by hand: the same for every variant trained on them,
so a comparison on them is fair, but they are not ground truth.

    python benchmarks/subject_masks.py CAPTURE MODEL(.ply|.pt) --out MASKED_CAPTURE
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import torch
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ao import load_model  # noqa: E402  (a run's PLY or checkpoint, as benchmarks/ao.py reads it)

from core.data import load_capture  # noqa: E402
from core.data.capture import Camera  # noqa: E402
from core.model import GaussianModel  # noqa: E402
from core.render import RenderCamera, render  # noqa: E402
from core.seeding import look_at_center  # noqa: E402


def fit_plane(points: np.ndarray, tol: float, rng: np.random.Generator,
              tries: int = 2000) -> tuple[np.ndarray, float]:
    """(unit normal n, offset d) of the plane n.x = d with the most points within `tol`,
    refined by least squares on those points."""
    best, best_count = None, -1
    for _ in range(tries):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        count = int((np.abs(points @ n - n @ a) < tol).sum())
        if count > best_count:
            best, best_count = (n, float(n @ a)), count
    n, d = best
    inliers = points[np.abs(points @ n - d) < tol]
    centre = inliers.mean(axis=0)
    n = np.linalg.svd(inliers - centre)[2][-1]
    return n, float(n @ centre)


def subject_gaussians(model: GaussianModel, cameras: list[Camera], margin: float, voxel: float,
                      seed: int = 0) -> tuple[np.ndarray, dict]:
    means = model.means.detach().numpy().astype(np.float64)
    opacity = model.opacity_c.detach().numpy().reshape(-1)
    centre = look_at_center(cameras)
    scale = float(np.median([np.linalg.norm(c.center - centre) for c in cameras]))
    opaque = opacity > 0.5
    n, d = fit_plane(means[opaque], 0.004 * scale, np.random.default_rng(seed))
    if np.mean([c.center for c in cameras], axis=0) @ n < d:  # face the cameras
        n, d = -n, -d
    height = means @ n - d
    cand = (height > margin * scale) & (opacity > 0.05)
    cells = np.floor(means[cand] / (voxel * scale)).astype(np.int64)
    lo = cells.min(axis=0)
    grid = np.zeros(cells.max(axis=0) - lo + 1, bool)
    grid[tuple((cells - lo).T)] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3, 3)))
    cell_label = labels[tuple((cells - lo).T)]
    dist = np.linalg.norm(means[cand] - centre, axis=1)
    near = cell_label[np.argsort(dist)[: max(1, len(dist) // 100)]]
    keep_label = np.bincount(near).argmax()  # the cluster of the Gaussians nearest the centre
    keep = np.zeros(len(means), bool)
    keep[np.flatnonzero(cand)[cell_label == keep_label]] = True
    info = {"gaussians": int(len(means)), "subject": int(keep.sum()), "clusters": int(count),
            "plane_inliers": int((np.abs(height[opaque]) < 0.004 * scale).sum()),
            "opaque": int(opaque.sum()), "camera_distance": scale}
    return keep, info


def _clean(mask: np.ndarray) -> np.ndarray:
    """The subject's region of a (H, W) bool mask: opened by a disc of 2% of the image's smaller
    side (cutting thin bridges to stray blobs, floaters seen at grazing angles), its largest
    region kept, grown back by the same disc within the original (thin fur and ears stay),
    holes filled."""
    k = max(3, round(0.02 * min(mask.shape)) | 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    opened = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, disc)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    if count <= 1:
        return mask
    core = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    kept = mask & (cv2.dilate(core, disc) > 0)
    return ndimage.binary_fill_holes(kept)


@torch.no_grad()
def view_mask(model: GaussianModel, cam: Camera, render_scale: float) -> np.ndarray:
    """(H, W) bool mask in the source camera's (distorted) pixels."""
    w, h = round(cam.width / render_scale), round(cam.height / render_scale)
    pinhole = Camera(cam.id, cam.width, cam.height, cam.K, cam.world_to_camera, None).scaled(w, h)
    alpha = render(model, RenderCamera.from_camera(pinhole), sh_degree=0,
                   geometry=False).alpha_c[..., 0].numpy()
    # Source pixel centres (OpenCV: integer) -> undistorted pixel of the pinhole render.
    K = cam.K.copy()
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    ys, xs = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1)[:, None]
    if cam.distortion is not None:
        pts = cv2.undistortPoints(pts, K, np.asarray(cam.distortion, np.float64), P=K)
    # Back to render pixels: centre at +0.5 in ours, scaled, then OpenCV's integer centres.
    u = (pts[:, 0, 0] + 0.5) * (w / cam.width) - 0.5
    v = (pts[:, 0, 1] + 0.5) * (h / cam.height) - 0.5
    src = cv2.remap(alpha.astype(np.float32), u.reshape(cam.height, cam.width).astype(np.float32),
                    v.reshape(cam.height, cam.width).astype(np.float32), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return _clean(src > 0.5)


def write_capture(capture, out: Path, masks: dict[tuple[str, str], np.ndarray]) -> None:
    out.mkdir(parents=True, exist_ok=False)
    shutil.copy2(capture.root / "capture.json", out / "capture.json")
    for (frame, cam_id), mask in masks.items():
        image = capture.image_path(frame, cam_id)
        (out / "images" / frame).mkdir(parents=True, exist_ok=True)
        (out / "masks" / frame).mkdir(parents=True, exist_ok=True)
        target = out / "images" / frame / image.name
        try:
            os.link(image, target)
        except OSError:
            shutil.copy2(image, target)
        cv2.imwrite(str(out / "masks" / frame / f"{cam_id}.png"), mask.astype(np.uint8) * 255)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("capture", type=Path)
    ap.add_argument("model", type=Path, help="a run's PLY or checkpoint (.pt) of that capture")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--margin", type=float, default=0.02,
                    help="height above the plane, fraction of the camera distance")
    ap.add_argument("--voxel", type=float, default=0.01, help="cluster voxel, same unit")
    ap.add_argument("--render-scale", type=float, default=2.0)
    ap.add_argument("--sheet", type=Path, default=None, help="write a contact sheet PNG")
    args = ap.parse_args()
    capture = load_capture(args.capture)
    model = load_model(args.model)
    keep, info = subject_gaussians(model, capture.cameras, args.margin, args.voxel)
    model.keep(torch.from_numpy(keep))
    masks, cover = {}, []
    for frame in capture.frames:
        for cam in capture.cameras:
            masks[frame, cam.id] = view_mask(model, cam, args.render_scale)
            cover.append(float(masks[frame, cam.id].mean()))
    write_capture(capture, args.out, masks)
    info.update(views=len(masks), coverage_mean=float(np.mean(cover)),
                coverage_min=float(np.min(cover)), coverage_max=float(np.max(cover)))
    (args.out / "masks.json").write_text(json.dumps({**info, "source": str(args.capture),
                                                     "model": str(args.model)}, indent=2))
    print(json.dumps(info, indent=2))
    if args.sheet:
        tiles = []
        for (frame, cam_id), mask in list(masks.items())[:: max(1, len(masks) // 12)][:12]:
            image = cv2.imread(str(capture.image_path(frame, cam_id)))
            image = cv2.resize(image, (mask.shape[1] // 6, mask.shape[0] // 6))
            m = cv2.resize(mask.astype(np.uint8), (image.shape[1], image.shape[0])) > 0
            tiles.append(np.where(m[..., None], image, (image * 0.25).astype(np.uint8)))
        tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % 6)
        cv2.imwrite(str(args.sheet),
                    np.vstack([np.hstack(tiles[i:i + 6]) for i in range(0, len(tiles), 6)]))


if __name__ == "__main__":
    main()
