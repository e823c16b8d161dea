"""`dgs export RUN --format ply|spz|stream`: deliver a run's frames.

- ply: the frame PLYs as they are (every 3DGS tool opens them): OUT/ply/<frame>.ply;
- spz: one SPZ per frame (appearance only, what web splat viewers read): OUT/spz/<frame>.spz;
- stream: the relightable sequence stream OUT/stream.dgss (docs/stream.md), one chunk per
  group of pictures of RUN/sequence.json (every frame its own group when the run has none),
  with the render settings, capture light and cameras a player needs in its header.

OUT/export.json records what was written: sizes, bytes per frame against the PLYs, seconds.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from core.config import parse_frames, read_run
from core.data import load_capture
from core.export.codec import StreamConfig
from core.export.splats import Splats, read_frame_ply, write_frame_ply
from core.export.subject import subject_rows
from core.export.spz import write_spz
from core.export.stream import write_stream
from core.relight.envmap import project_sh9
from core.relight.presets import BUILTIN_PREFIX, PRESETS, builtin_radiance
from core.stages import plan

__all__ = ["FORMATS", "export_run", "stream_header"]

FORMATS = ("ply", "spz", "stream")


def _run_frames(run: Path) -> tuple[list[str], list[list[str]]]:
    """(finished frames in order, their groups) from RUN/sequence.json, or one group per frame."""
    done = sorted(p.parent.name for p in (run / "frames").glob("*/gaussians.ply"))
    seq_path = run / "sequence.json"
    if seq_path.is_file():
        seq = json.loads(seq_path.read_text())
        groups = [[f for f in g["frames"] if f in done] for g in seq.get("gops", [])]
        groups = [g for g in groups if g]
        listed = {f for g in groups for f in g}
        groups += [[f] for f in done if f not in listed]
        groups.sort(key=lambda g: g[0])
    else:
        groups = [[f] for f in done]
    return [f for g in groups for f in g], groups


def stream_header(run: Path, frames: list[str], fps: float | None,
                  capture_dir: str | os.PathLike[str] | None = None) -> dict:
    """What a player needs besides the Gaussians: frame names and rate, how the run renders
    (SH degree, beta, screen blur, background, sRGB or linear colour), the capture light the
    albedo is divided by (uniform pi, docs/design.md section 5) and the capture's cameras (at the
    run's resolution) and up axis."""
    resolved = read_run(run, capture_dir)
    train, views = resolved.config.train, resolved.views
    p = plan(train.schedule.iterations - 1, train.schedule, train.method)
    header = {"frames": frames, "render": {
        "sh_degree": p.sh_degree, "beta": p.beta, "eps2d": train.eps2d,
        "antialiased": train.antialiased, "background": list(train.background),
        "linear": False}, "capture_light": {"uniform": math.pi}, "up": [0.0, 0.0, 1.0],
        "cameras": []}
    capture_path = Path(capture_dir if capture_dir is not None else resolved.capture)
    meta = {}
    if (capture_path / "capture.json").is_file():
        capture = load_capture(capture_path)
        meta = json.loads((capture_path / "capture.json").read_text())
        header["up"] = [float(v) for v in capture.up]
        scored = set(views.split.scored)
        for c in capture.cameras:
            s = views.served(c)
            header["cameras"].append({"id": s.id, "width": s.width, "height": s.height,
                                      "K": s.K.tolist(), "world_to_camera":
                                      s.world_to_camera.tolist(), "heldout": c.id in scored})
        first = capture.image_path(capture.frames[0], capture.cameras[0].id)
        header["render"]["linear"] = first is not None and first.suffix.lower() == ".exr"
    header["envmaps"] = _builtin_sh9()
    rate = fps if fps is not None else meta.get("fps", 24.0)
    if not (isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0):
        raise ValueError(f"fps: expected a frame rate > 0, got {rate!r}")
    header["fps"] = float(rate)
    return header


def _builtin_sh9() -> dict[str, list]:
    """The built-in maps' SH9 radiance in their own frame (poles on +z, unrotated): the player
    turns them into the capture's up frame and rotates them as the relight job does."""
    return {BUILTIN_PREFIX + name: np.round(project_sh9(builtin_radiance(name)), 7).tolist()
            for name in PRESETS}


def _frames(run: Path, out: Path, groups: list[list[str]], subject: bool,
            capture_dir) -> tuple[Callable[[str], Splats], dict]:
    """(a reader of each frame's Splats, the record's start). With `subject` the frames are the
    subject's (`core.export.subject`), written as OUT/ply/<frame>.ply, which is also what
    the size a frame is measured on."""
    order = [f for g in groups for f in g]
    rows = subject_rows(run, groups, capture_dir) if subject else None

    def frame(f: str) -> Splats:
        splats = read_frame_ply(run / "frames" / f / "gaussians.ply")
        return splats if rows is None else splats.take(rows[f])

    if rows is not None:
        (out / "ply").mkdir(exist_ok=True)
        for f in order:
            write_frame_ply(out / "ply" / f"{f}.ply", frame(f))
    ply_bytes = [(out / "ply" / f"{f}.ply" if rows is not None else
                  run / "frames" / f / "gaussians.ply").stat().st_size for f in order]
    record: dict = {"run": str(run), "frames": order,
                    "ply_bytes_per_frame": float(np.mean(ply_bytes))}
    if rows is not None:
        kept = [int(rows[f].sum()) for f in order]
        record["subject"] = {"gaussians_per_frame": float(np.mean(kept)),
                             "share": float(sum(kept) / sum(len(rows[f]) for f in order))}
    return frame, record


def export_run(run_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str], *,
               formats: Sequence[str] = ("stream",), frames: str | None = None,
               fps: float | None = None, config: StreamConfig = StreamConfig(),
               capture_dir: str | os.PathLike[str] | None = None,
               on_progress: Callable[[str, int, int], None] | None = None,
               subject: bool = False, run_name: str | None = None) -> dict:
    """Export `run_dir` into `out_dir` in each of `formats`; returns (and writes as
    OUT/export.json) the record. `frames` (a slice) keeps whole groups for the stream: a group
    is cut where the slice cuts it, its first kept frame becoming the key frame. `subject`:
    only the Gaussians inside the subject masks' hull (`core.export.subject`). `run_name` is
    how the record names the run (default: its folder; a service gives the job's id)."""
    run, out = Path(run_dir), Path(out_dir)
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise ValueError(f"formats: expected some of {', '.join(FORMATS)}, got {list(formats)}")
    read_run(run, capture_dir)  # a run directory, its record readable, before anything
    order, groups = _run_frames(run)
    if not order:
        raise ValueError(f"run_dir: {run} has no finished frame (frames/<frame>/gaussians.ply)")
    chosen = set(parse_frames(frames, order))
    groups = [[f for f in g if f in chosen] for g in groups]
    groups = [g for g in groups if g]
    order = [f for g in groups for f in g]
    out.mkdir(parents=True, exist_ok=True)
    frame, record = _frames(run, out, groups, subject, capture_dir)
    record["run"] = run_name or str(run)
    record["formats"] = list(formats)
    total = len(order) * len(formats)
    done = 0

    def step(what: str) -> None:
        nonlocal done
        done += 1
        if on_progress is not None:
            on_progress(what, done, total)

    if "ply" in formats:
        for f in order:
            (out / "ply").mkdir(exist_ok=True)
            if not subject:
                shutil.copyfile(run / "frames" / f / "gaussians.ply", out / "ply" / f"{f}.ply")
            step(f"ply {f}")
    header = stream_header(run, order, fps, capture_dir)
    sh_dim = (header["render"]["sh_degree"] + 1) ** 2 - 1
    if "spz" in formats:
        (out / "spz").mkdir(exist_ok=True)
        start, sizes = time.perf_counter(), []
        for f in order:
            sizes.append(write_spz(out / "spz" / f"{f}.spz", frame(f),
                                   sh_degree=header["render"]["sh_degree"]))
            step(f"spz {f}")
        record["spz"] = {"bytes_per_frame": float(np.mean(sizes)),
                         "ratio_to_ply": record["ply_bytes_per_frame"] / float(np.mean(sizes)),
                         "encode_seconds_per_frame": (time.perf_counter() - start) / len(order)}
    if "stream" in formats:
        record["stream"] = _write_stream(out, groups, header, config, sh_dim, step, frame)
        record["stream"]["ratio_to_ply"] = (record["ply_bytes_per_frame"]
                                            / record["stream"]["bytes_per_frame"])
    tmp = out / "export.json.tmp"
    tmp.write_text(json.dumps(record, indent=2) + "\n")
    os.replace(tmp, out / "export.json")
    return record


def _write_stream(out: Path, groups: list[list[str]], header: dict, config: StreamConfig,
                  sh_dim: int, step, frame: Callable[[str], Splats]) -> dict:
    splats = []
    for g in groups:
        splats.append([])
        for f in g:
            splats[-1].append(frame(f))
            step(f"stream {f}")
    header = {**header, "tolerances": asdict(config)}
    stats = write_stream(out / "stream.dgss", splats, header, config, sh_dim=sh_dim)
    frames = sum(len(g) for g in groups)
    return {"path": "stream.dgss", "bytes": stats.bytes, "groups": len(groups),
            "bytes_per_frame": stats.bytes / frames, "group_bytes": stats.group_bytes,
            "encode_seconds_per_frame": stats.encode_seconds / frames,
            "frame_meta": stats.frame_meta}
