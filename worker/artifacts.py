"""What each file of a run directory is, for the typed artifact listing (DESIGN.md 3.3)."""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["ArtifactKind", "CONTENT_TYPES", "KINDS", "classify"]

CONTENT_TYPES = {".png": "image/png", ".json": "application/json", ".ply": "application/x-ply",
                 ".npy": "application/x-npy", ".mp4": "video/mp4", ".exr": "image/x-exr",
                 ".obj": "model/obj", ".glb": "model/gltf-binary", ".jpg": "image/jpeg",
                 ".dgss": "application/octet-stream", ".spz": "application/octet-stream"}

# (pattern on the path relative to the run directory, kind); the first match wins.
_RULES: tuple[tuple[str, str], ...] = (
    (r"frames/(?P<frame>[^/]+)/gaussians\.ply", "ply"),
    (r"meshes/(?P<frame>[^/]+)\.(ply|obj|glb)", "mesh"),
    (r"renders/(?P<frame>[^/]+)/[^/]+_rgb\.png", "render"),
    (r"renders/(?P<frame>[^/]+)/[^/]+_normal\.png", "normal"),
    (r"renders/(?P<frame>[^/]+)/[^/]+_ao\.png", "ao"),
    (r"renders/(?P<frame>[^/]+)/[^/]+_depth\.npy", "depth"),
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
    (r"[^/]+\.png", "image"),
)
KINDS = tuple(dict.fromkeys(kind for _, kind in _RULES))


@dataclass(frozen=True)
class ArtifactKind:
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
