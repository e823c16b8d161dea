"""The run directory (docs/design.md section 3.3): where each output of a run lives, what kind
of artifact each file is, and its reads and writes (atomic, so a reader never sees half a
file). Every module that reads or writes a run goes through `RunDir`; the worker's artifact
listing classifies files with `classify`. Torch-free.

    RUN/config.json                      the resolved run (`core.config.ResolvedRun`)
    RUN/metrics.json                     per-frame records (`core.pipeline.record.FrameRecord`)
    RUN/sequence.json                    groups, roles and timings of a sequence
    RUN/eval.json                        held-out scores (`dgs eval`)
    RUN/frames/<frame>/gaussians.ply     the frame's Gaussians (3DGS PLY + geometry branch)
    RUN/renders/<frame>/<camera>_{rgb,normal,ao,relit}.png, <camera>_depth.npy
    RUN/meshes/<frame>.{ply,obj,glb}
    RUN/plots/*.png                      training curves; seeds-<frame>.png, a key frame's seeds
    RUN/seeds/static.ply                 the static scene's seeds later key frames keep
    RUN/checkpoints/<frame>.pt           training state of an unfinished frame
    RUN/carried.json                     frames finished by another process (`core.pipeline.carry`)
    RUN/frames/<frame>/tracks.npz        a carried frame's track ids and positions
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from core.config.resolved import ResolvedRun, read_run
from core.files import atomic_path, write_json

__all__ = ["ARTIFACT_KINDS", "CONTENT_TYPES", "ArtifactKind", "RunDir", "classify",
           "save_array"]

CONTENT_TYPES = {".png": "image/png", ".json": "application/json", ".ply": "application/x-ply",
                 ".npy": "application/x-npy", ".mp4": "video/mp4", ".exr": "image/x-exr",
                 ".obj": "model/obj", ".glb": "model/gltf-binary", ".jpg": "image/jpeg",
                 ".dgss": "application/octet-stream", ".spz": "application/octet-stream"}

# (pattern on the path relative to the run directory, kind); the first match wins. Which
# pipeline writes each kind is the pipeline registry's to say (`worker.pipelines.PIPELINES`).
_RULES: tuple[tuple[str, str], ...] = (
    (r"frames/(?P<frame>[^/]+)/gaussians\.ply", "ply"),
    (r"meshes/(?P<frame>[^/]+)\.(ply|obj|glb)", "mesh"),
    (r"renders/(?P<frame>[^/]+)/[^/]+_rgb\.png", "render"),
    (r"renders/(?P<frame>[^/]+)/[^/]+_normal\.png", "normal"),
    (r"renders/(?P<frame>[^/]+)/[^/]+_ao\.png", "ao"),
    (r"renders/(?P<frame>[^/]+)/[^/]+_depth\.npy", "depth"),
    # the evaluation's relit held-out views (a synthetic capture's second light)
    (r"renders/(?P<frame>[^/]+)/[^/]+_relit\.png", "relit"),
    (r"relit/(?P<frame>[^/]+)/[^/]+\.(png|exr)", "relit"),
    (r"relit/(?P<frame>[^/]+)\.mp4", "video"),
    (r"relit/videos/[^/]+\.mp4", "video"),
    (r"relit/relight\.json", "relight"),
    (r"export/stream\.dgss", "stream"),
    (r"export/spz/(?P<frame>[^/]+)\.spz", "spz"),
    (r"export/ply/(?P<frame>[^/]+)\.ply", "ply"),
    (r"export/export\.json", "export"),
    (r"plots/[^/]+\.png", "plot"),
    (r"config\.json", "config"),
    (r"(metrics|sequence)\.json", "metrics"),
    (r"eval\.json", "eval"),
    (r"[^/]+\.png", "image"),  # the contact sheet
)
ARTIFACT_KINDS = tuple(dict.fromkeys(kind for _, kind in _RULES))


@dataclass(frozen=True)
class ArtifactKind:
    """What a published file is."""

    kind: str
    content_type: str
    frame: str | None


def classify(rel: str) -> ArtifactKind | None:
    """The kind of `rel` (a '/'-path in a run directory), or None for what is not published
    (checkpoints, temporary files)."""
    if rel.startswith("checkpoints/") or rel.endswith((".tmp", ".part")):
        return None
    for pattern, kind in _RULES:
        m = re.fullmatch(pattern, rel)
        if m:
            ext = rel[rel.rfind("."):].lower()
            return ArtifactKind(kind, CONTENT_TYPES.get(ext, "application/octet-stream"),
                                m.groupdict().get("frame"))
    return None


class RunDir:
    """A run directory's layout and its JSON records (module docstring)."""

    def __init__(self, root: str | os.PathLike[str]):
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"RunDir({str(self.root)!r})"

    # -- layout ------------------------------------------------------------------------------
    @property
    def config(self) -> Path:
        return self.root / "config.json"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def sequence(self) -> Path:
        return self.root / "sequence.json"

    @property
    def eval(self) -> Path:
        return self.root / "eval.json"

    @property
    def plots(self) -> Path:
        return self.root / "plots"

    @property
    def meshes(self) -> Path:
        return self.root / "meshes"

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    def frame_dir(self, frame: str) -> Path:
        return self.root / "frames" / frame

    def ply(self, frame: str) -> Path:
        """The frame's Gaussians; it exists once the frame is finished."""
        return self.frame_dir(frame) / "gaussians.ply"

    def renders(self, frame: str) -> Path:
        return self.root / "renders" / frame

    def mesh(self, frame: str, fmt: str = "ply") -> Path:
        return self.meshes / f"{frame}.{fmt}"

    def static_seeds(self) -> Path:
        """The static scene's seeds of the run's first key frame (`core.seeding`)."""
        return self.root / "seeds" / "static.ply"

    def checkpoint(self, frame: str) -> Path:
        return self.checkpoints / f"{frame}.pt"

    def finished(self, frames: list[str] | tuple[str, ...]) -> list[str]:
        """The frames of `frames` whose PLY is written, in order."""
        return [f for f in frames if self.ply(f).is_file()]

    # -- records -----------------------------------------------------------------------------
    def read_run(self, capture_dir: str | os.PathLike[str] | None = None) -> ResolvedRun:
        """RUN/config.json as the run it records (`core.config.read_run`: `capture_dir` only
        for a record of an older version); ValueError when this is not a run directory."""
        return read_run(self.root, capture_dir)

    def read_metrics(self) -> dict[str, Any]:
        """RUN/metrics.json ({} before the first frame is finished)."""
        return json.loads(self.metrics.read_text()) if self.metrics.is_file() else {}

    def read_carried(self) -> set[str]:
        """The frames finished by another process whose outputs did not come along
        (RUN/carried.json, `core.pipeline.carry`): finished, but not here to score."""
        path = self.root / "carried.json"
        return set(json.loads(path.read_text())["frames"]) if path.is_file() else set()

    def read_sequence(self) -> dict[str, Any] | None:
        return json.loads(self.sequence.read_text()) if self.sequence.is_file() else None

    def write(self, name: str, data: Any) -> Path:
        """RUN/<name> as JSON, atomically (name: config.json, metrics.json, ...)."""
        path = self.root / name
        write_json(path, data)
        return path

    def check_new_or_resumable(self, resume: bool) -> None:
        """ValueError unless the folder is new or empty, or (with `resume`) a run directory."""
        root = self.root
        if not root.exists() or (root.is_dir() and not any(root.iterdir())):
            return
        if not root.is_dir():
            raise ValueError(f"out: {root} exists and is not a folder")
        if not resume:
            raise ValueError(f"out: {root} already exists and is not empty; pass --resume to "
                             "continue a run there, or choose another folder")
        if not self.config.is_file():
            raise ValueError(f"out: {root} is not a run directory (no config.json); cannot "
                             "resume")


def save_array(path: str | os.PathLike[str], array) -> None:
    """An .npy file, atomically."""
    with atomic_path(path, suffix=".tmp.npy") as tmp:
        np.save(tmp, array)
