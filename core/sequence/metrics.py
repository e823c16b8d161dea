"""Temporal metrics of a run for `eval.json` (issue: volumetric video).

Flicker compares what changes between consecutive frames in the renders with what changes in the
ground truth: per held-out view and consecutive pair (t-1, t), over pixels on the figure in both
frames' ground truth,

    flicker = mean |(R_t - R_{t-1}) - (G_t - G_{t-1})|

for the normal map (unit normals decoded from the PNG, components averaged; uncovered pixels
count as the zero vector) and the AO map (0..1). A method whose renders follow the true motion
and nothing else scores 0; `change` and `gt_change` (mean |R_t - R_{t-1}|, mean |G_t - G_{t-1}|)
are reported beside it. The largest PSNR drop between consecutive frames of one group
(RUN/sequence.json) is reported too, and at the groups' boundaries the largest drop into a key
frame and the boundary pairs' flicker against the in-group pairs', and where the ground truth has correspondences, how far
tracked Gaussians drift from the points they were born on (`core.sequence.correspondence`).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from core.sequence.correspondence import track_errors

__all__ = ["temporal_metrics"]


def _png(path: Path) -> np.ndarray | None:
    if not path.is_file():
        return None
    return np.asarray(Image.open(path)).astype(np.float32) / 255.0


def _resize(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    if a.shape[:2] == shape:
        return a

    return cv2.resize(a, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)


def _maps(run: Path, gt: Path, frame: str, cam: str) -> dict | None:
    """Rendered and true normal / AO maps of one view and its figure region; None when missing."""
    normal_png = _png(run / "renders" / frame / f"{cam}_normal.png")
    ao_png = _png(run / "renders" / frame / f"{cam}_ao.png")
    gt_n_path = gt / "normals" / frame / f"{cam}.npy"
    if normal_png is None or ao_png is None or not gt_n_path.is_file():
        return None
    shape = normal_png.shape[:2]
    gt_n = _resize(np.load(gt_n_path).astype(np.float32), shape)
    region = np.linalg.norm(gt_n, axis=-1) > 0.5
    gt_n = gt_n / np.maximum(np.linalg.norm(gt_n, axis=-1, keepdims=True), 1e-6)
    covered = normal_png[..., :3].max(axis=-1, keepdims=True) > 0
    n = normal_png[..., :3] * 2 - 1
    n = np.where(covered, n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6), 0.0)
    gt_ao = _png(gt / "visibility" / frame / f"{cam}.png")
    ao = ao_png if ao_png.ndim == 2 else ao_png[..., 0]
    if gt_ao is not None:
        gt_ao = _resize(gt_ao if gt_ao.ndim == 2 else gt_ao[..., 0], shape)
    return {"normal": n, "gt_normal": gt_n, "ao": ao, "gt_ao": gt_ao, "region": region}


def _pair(a: dict, b: dict) -> dict:
    region = a["region"] & b["region"]
    if not region.any():
        return {}
    dn, dg = b["normal"] - a["normal"], b["gt_normal"] - a["gt_normal"]
    out = {"normal": float(np.abs(dn - dg)[region].mean()),
           "normal_change": float(np.abs(dn)[region].mean()),
           "normal_gt_change": float(np.abs(dg)[region].mean())}
    if a["gt_ao"] is not None and b["gt_ao"] is not None:
        da, dga = b["ao"] - a["ao"], b["gt_ao"] - a["gt_ao"]
        out.update(ao=float(np.abs(da - dga)[region].mean()),
                   ao_change=float(np.abs(da)[region].mean()),
                   ao_gt_change=float(np.abs(dga)[region].mean()))
    return out


def _mean(rows: list[dict], key: str) -> float | None:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(vals)) if vals else None


def _groups(run: Path) -> dict[str, int]:
    """Each frame's group (sequence.json; {} without one)."""
    path = run / "sequence.json"
    if not path.is_file():
        return {}
    return {r["frame"]: r["gop"] for r in json.loads(path.read_text())["frames"]}


def _largest_drop(group: dict[str, int], per_frame: list[dict], across: bool) -> float | None:
    """Largest PSNR decrease between consecutive frames of one group, or (`across`) between a
    group's last frame and the next group's key frame."""
    psnr = {r["frame"]: r.get("psnr") for r in per_frame}
    order = [r["frame"] for r in per_frame]
    drops = [psnr[a] - psnr[b] for a, b in zip(order, order[1:])
             if a in group and b in group and (group[a] != group[b]) == across
             and None not in (psnr[a], psnr[b])]
    return float(max(drops)) if drops else None


def _boundaries(group: dict[str, int], pairs: list[dict], per_frame: list[dict]) -> dict:
    """How the group boundaries compare with the inside of the groups: the largest PSNR drop
    into a key frame, and the flicker of boundary pairs against in-group pairs."""
    def flicker(rows: list[dict]) -> float | None:
        both = [v for v in (_mean(rows, "normal"), _mean(rows, "ao")) if v is not None]
        return float(np.mean(both)) if both else None

    edge = [p for p in pairs if group.get(p["frames"][0]) != group.get(p["frames"][1])]
    inside = [p for p in pairs if group.get(p["frames"][0]) == group.get(p["frames"][1])]
    at, within = flicker(edge), flicker(inside)
    return {"count": len(edge), "largest_psnr_drop": _largest_drop(group, per_frame, True),
            "flicker": at, "flicker_inside": within,
            "flicker_ratio": None if at is None or not within else at / within}


def temporal_metrics(run_dir, capture_dir, frames: list[str], cameras: list[str],
                     per_frame: list[dict]) -> dict:
    """Flicker of the normal and AO maps over consecutive `frames` (held-out `cameras`) against
    the capture's ground truth (gt/normals, gt/visibility; flicker is None without it), the
    per-frame PSNR and normal cosine as lists, and the largest in-group PSNR drop."""
    run, gt = Path(run_dir), Path(capture_dir) / "gt"
    pairs = []
    for a, b in zip(frames, frames[1:]):
        rows = []
        for cam in cameras:
            ma, mb = _maps(run, gt, a, cam), _maps(run, gt, b, cam)
            if ma is not None and mb is not None:
                r = _pair(ma, mb)
                if r:
                    rows.append(r)
        if rows:
            pairs.append({"frames": [a, b], **{k: _mean(rows, k) for k in rows[0]}})
    group = _groups(run)
    fn, fa = _mean(pairs, "normal"), _mean(pairs, "ao")
    both = [v for v in (fn, fa) if v is not None]
    return {
        "flicker": float(np.mean(both)) if both else None,
        "flicker_normal": fn, "flicker_ao": fa,
        "normal_change": _mean(pairs, "normal_change"),
        "normal_gt_change": _mean(pairs, "normal_gt_change"),
        "ao_change": _mean(pairs, "ao_change"), "ao_gt_change": _mean(pairs, "ao_gt_change"),
        "psnr_per_frame": [r.get("psnr") for r in per_frame],
        "normal_cos_per_frame": [r.get("normal_cos") for r in per_frame],
        "largest_psnr_drop_in_group": _largest_drop(group, per_frame, False),
        "boundaries": _boundaries(group, pairs, per_frame) if group else None,
        **(track_errors(run, capture_dir) or {"track_error": None}),
        "pairs": pairs,
    }
