"""What every finished frame writes besides its PLY: the held-out views (colour, normals, AO,
depth) at the training resolution, and its mesh."""

from __future__ import annotations

import numpy as np
import torch

from core.color import linear_to_srgb
from core.config import MeshConfig, Views
from core.data.dataset import CaptureDataset
from core.data.images import write_png
from core.mesh import mesh_run
from core.render import RenderCamera, render, safe_divide
from core.rundir import RunDir, save_array
from core.stages import plan
from core.training import FrameFitter

__all__ = ["COVERAGE", "mesh_frame", "render_heldout", "thin"]

# Geometry coverage above which a pixel gets a normal and AO in the pictures (else black): low
# enough that the soft edges of a short run still show, high enough that the direction of the
# alpha-weighted normal sum is not noise.
COVERAGE = 0.2


def _to8(a: np.ndarray) -> np.ndarray:
    return (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)


@torch.no_grad()
def render_heldout(capture, frame: str, fitter: FrameFitter, run: RunDir,
                   views: Views) -> list[str]:
    """Write <camera>_rgb.png, _normal.png, _ao.png and _depth.npy of the cameras the run's
    `views` score (the held-out ones, or the training ones when none is held out) into
    RUN/renders/<frame>/ at the training resolution; returns their ids."""
    cfg = fitter.config
    p = plan(cfg.schedule.iterations - 1, cfg.schedule, cfg.method)
    device = fitter.model.device
    bg = torch.tensor(cfg.background, dtype=torch.float32, device=device)
    out, ids = run.renders(frame), []
    served = CaptureDataset(capture, frames=[frame], downscale=views.downscale).served_camera
    for cam in views.cameras(capture, "scored"):
        camera = RenderCamera.from_camera(served(cam), device=device, near=fitter.near)
        r = render(fitter.model, camera, sh_degree=p.sh_degree, beta=p.beta, geometry=True,
                   tie_opacity=False, background=bg, eps2d=cfg.eps2d,
                   antialiased=cfg.antialiased)
        rgb = r.rgb.clamp(0, 1).cpu().numpy()
        image = capture.image_path(frame, cam.id)
        if image is not None and image.suffix.lower() == ".exr":
            rgb = linear_to_srgb(rgb)  # the capture is linear: encode it
        covered = (r.alpha_g > COVERAGE).cpu().numpy()
        # Training leaves the normal map unnormalized (docs/design.md 5.3); the picture shows
        # directions.
        n = torch.nn.functional.normalize(r.normal, dim=-1).cpu().numpy()
        ao = safe_divide(r.visibility, r.alpha_g).clamp(0, 1).cpu().numpy()
        write_png(out / f"{cam.id}_rgb.png", _to8(rgb))
        write_png(out / f"{cam.id}_normal.png", _to8(np.where(covered, (n + 1) / 2, 0.0)))
        write_png(out / f"{cam.id}_ao.png", _to8(np.where(covered, ao, 0.0)))
        save_array(out / f"{cam.id}_depth.npy",
                   r.depth[..., 0].cpu().numpy().astype(np.float32))
        ids.append(cam.id)
    return ids


def mesh_frame(run: RunDir, capture, frame: str, settings: MeshConfig) -> dict | None:
    """RUN/meshes/<frame>.<fmt> (kept when a resumed run already wrote them); its statistics, or
    {"error": ...} when the frame has no surface to mesh (the run goes on)."""
    if not settings.enabled:
        return None
    result = mesh_run(run.root, frames=[frame], config=settings, capture_dir=capture.root,
                      skip_existing=True, errors="record")
    return result["frames"].get(frame)


def thin(records: list[dict], keep: int = 2000) -> list[dict]:
    """At most about `keep` records (every k-th and the last) so metrics.json stays small."""
    k = max(1, -(-len(records) // keep))
    out = records[::k]
    if records and out[-1] is not records[-1]:
        out.append(records[-1])
    return [{key: (round(v, 6) if isinstance(v, float) else v) for key, v in r.items()}
            for r in out]
