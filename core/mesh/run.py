"""`mesh_run`: meshes of a run's finished frames (what `dgs mesh` and `dgs reconstruct` call),
written in the capture's original coordinates.

A capture made by `dgs capture import` keeps the transform back to its source in its import
record (`import.to_source.source_from_world`, core.data.importers.common.source_transform);
meshes are written in that source frame so they line up with the source's own data. Captures
without an import record (e.g. `dgs synth`) are their own source: meshes stay in world
coordinates. OUT/meshes.json records, per frame, the transform applied and the mesh statistics.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from core.config import MeshConfig, Views, parse_frames
from core.data import load_capture
from core.export.subject import subject_rows
from core.files import write_json
from core.mesh.build import mesh_model
from core.mesh.surface import export_mesh, transform_mesh
from core.model import GaussianModel
from core.relight.gbuffer import run_render

__all__ = ["mesh_run", "source_from_world", "training_views"]


def source_from_world(capture) -> np.ndarray | None:
    """The 4x4 from capture world to the source's coordinates, or None when there is none (or it
    is the identity)."""
    record = capture.import_record or {}
    m = (record.get("to_source") or {}).get("source_from_world")
    if m is None:
        return None
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"capture: import.to_source.source_from_world in {capture.root} is not "
                         "a finite 4x4 matrix")
    return None if np.allclose(m, np.eye(4)) else m


def training_views(capture, views: Views) -> list:
    """The run's training cameras (`views`) at its resolution."""
    return [views.served(c) for c in views.cameras(capture, "training")]


def _chosen(frames, finished: list[str]) -> list[str]:
    if frames is None or isinstance(frames, str):
        return parse_frames(frames, finished)
    missing = [f for f in frames if f not in finished]
    if missing:
        raise ValueError(f"frames: {', '.join(missing)} not finished in the run")
    if not frames:
        raise ValueError("frames: the list selects no frame")
    return list(frames)


def mesh_run(run_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str] | None = None, *,
             frames: str | Sequence[str] | None = None, config: MeshConfig = MeshConfig(),
             capture_dir=None, skip_existing: bool = False,
             errors: Literal["raise", "record"] = "raise",
             on_start: Callable[[list[str]], None] | None = None,
             on_frame: Callable[[str, dict], None] | None = None) -> dict:
    """Mesh the selected finished frames ('A:B' over them, or a list of names; None: all) into
    OUT/<frame>.<fmt> (default OUT = RUN/meshes); returns {"out", "frames": {frame: info}} (also
    OUT/meshes.json). `skip_existing` keeps frames whose files are all there (a resumed run);
    `errors="record"` writes a frame's ValueError into its info instead of raising (what
    `dgs reconstruct` does: a frame with no surface yet must not fail the run).
    `on_start(frames)` is called once the inputs are checked, `on_frame(frame, info)` after each
    frame."""
    if errors not in ("raise", "record"):
        raise ValueError(f"errors: expected 'raise' or 'record', got {errors!r}")
    run = Path(run_dir)
    settings = run_render(run, capture_dir)
    capture = load_capture(settings.capture)
    finished = [f for f in capture.frames if (run / "frames" / f / "gaussians.ply").is_file()]
    if not finished:
        raise ValueError(f"run_dir: {run} has no finished frame (no frames/<frame>/gaussians.ply)")
    chosen = _chosen(frames, finished)
    out = Path(out_dir) if out_dir is not None else run / "meshes"
    to_source = source_from_world(capture)
    cameras = training_views(capture, settings.views)
    first = capture.image_path(capture.frames[0], capture.cameras[0].id)
    linear = first is not None and first.suffix.lower() == ".exr"
    old = {}
    if skip_existing and (out / "meshes.json").is_file():
        old = json.loads((out / "meshes.json").read_text()).get("frames", {})
    result = {"version": 1, "out": str(out), "config": asdict(config),
              "to_source": None if to_source is None else to_source.tolist(), "frames": old}
    if on_start is not None:
        on_start(chosen)
    for frame in chosen:
        if skip_existing and all((out / f"{frame}.{fmt}").is_file() for fmt in config.formats):
            continue
        start = time.perf_counter()
        model = GaussianModel.load_ply(run / "frames" / frame / "gaussians.ply")
        try:
            if config.subject:
                rows = subject_rows(run, [[frame]], capture_dir)[frame]
                model.keep(torch.from_numpy(rows))
            mesh, info = mesh_model(model, cameras, settings, config, linear_capture=linear,
                                    up=capture.up)
        except ValueError as exc:
            if errors == "raise":
                raise ValueError(f"frame {frame}: {exc}") from None
            info = {"error": str(exc)}
        else:
            files = export_mesh(transform_mesh(mesh, to_source), out / frame, config.formats)
            info["files"] = [p.name for p in files]
            info["seconds"]["with_export"] = round(time.perf_counter() - start, 3)
        result["frames"][frame] = info
        write_json(out / "meshes.json", result)
        if on_frame is not None:
            on_frame(frame, info)
    return result
