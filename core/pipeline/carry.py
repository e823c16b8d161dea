"""A sequence run carried from one machine to the next (docs/design.md 5.9): what a run cut
short by a time limit must hand on so that another process, elsewhere, continues it to the
result the uninterrupted run gives.

A tracked frame reads, besides the run's records (metrics.json: track ids, deform losses, the
refine budget), only its previous frame's Gaussians and the positions and track ids of the two
frames before that (its motion starts); its deformation graph is rebuilt from the previous
frame's Gaussians, deterministically. A key frame reads nothing of the frames before it, but a
later key frame of a scene around a subject keeps the static scene the run's first key frame
seeded (RUN/seeds/static.ply), which the next call's capture need not hold the frame to make
again. So `pack_resume` writes:

- resume.json: config.json, metrics.json and sequence.json, and what the array files hold;
- for the next frame to run, when it is a tracked frame: its previous frame's Gaussians (every
  parameter and the track ids), and the earlier frames' positions and ids, as compressed
  .npz files (lossless), split by rows so that no file exceeds `part_bytes` (a lent machine
  returns files of at most 16 MiB). Only when the lossless files exceed `budget` are the
  higher SH coefficients (shN, 45 of a Gaussian's 64 values) stored as float16, which
  resume.json then says (`lossy`);
- the static seeds, when the run has them, byte for byte (`resume--static-N.npz`: no frame's
  name starts with a hyphen), outside the budget (a point is 15 bytes).

`unpack_resume` lays those files out as a run directory that `reconstruct(resume=True)`
continues: the records, the previous frame's PLY (bit for bit the original), the earlier
frames' tracks (frames/<frame>/tracks.npz), the static seeds, and RUN/carried.json naming the
frames finished elsewhere, which the run does not redo and `dgs eval` does not score (their
renders stayed with the run that made them).

`FrameBudget` ends a run with a time limit at a frame boundary, where it has the least to carry.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from core.config import ResolvedRun
from core.plyio import read_gaussian_ply, read_track_ids, write_gaussian_ply
from core.rundir import RunDir
from core.sequence.plan import GopPlan
from core.sequence.tracks import frame_tracks

__all__ = ["PART_BYTES", "FrameBudget", "pack_resume", "unpack_resume"]

PART_BYTES = 15 * 2**20
"""Largest array file (a lent machine returns files of at most 16 MiB)."""
STATIC_STEM = "resume--static"
"""The static seeds' files (a frame's are resume-<frame>-N.npz)."""
_NAME = re.compile(r"[^A-Za-z0-9._-]")


def _next_frame(run: RunDir, resolved: ResolvedRun) -> tuple[GopPlan, dict, int | None]:
    cfg = resolved.config
    records = run.read_metrics().get("frames", {})
    plan = GopPlan(list(resolved.frames), cfg.gop, cfg.sequence, cfg.train.schedule.iterations)
    todo = [i for i, r in enumerate(plan.roles) if r.frame not in records]
    return plan, records, (todo[0] if todo else None)


def _arrays(run: RunDir, frame: str, kind: str) -> dict[str, np.ndarray]:
    if kind == "tracks":
        ids, means = frame_tracks(run, frame)
        return {"ids": ids.astype(np.int64), "means": means.astype(np.float32)}
    params = read_gaussian_ply(run.ply(frame))
    ids = read_track_ids(run.ply(frame))
    n = params["means"].shape[0]
    return {**params, "ids": (np.arange(n) if ids is None else ids).astype(np.int64)}


def _write_parts(out: Path, stem: str, arrays: dict[str, np.ndarray], part_bytes: int
                 ) -> list[str]:
    n = next(iter(arrays.values())).shape[0]
    row = max(1, sum(a[:1].nbytes for a in arrays.values()))
    # The raw size bounds the compressed one; up to 64 KiB (half a small part) for the zip's
    # headers and deflate's worst case on incompressible floats.
    rows = max(1, (part_bytes - min(65536, part_bytes // 2)) // row)
    names = []
    for k, start in enumerate(range(0, max(n, 1), rows)):
        name = f"{stem}-{k}.npz"
        with open(out / name, "wb") as f:
            np.savez_compressed(f, **{key: a[start:start + rows] for key, a in arrays.items()})
        names.append(name)
    return names


def _needs(plan: GopPlan, records: dict, index: int | None) -> dict[str, str]:
    """{frame: "full" | "tracks"}: what the next frame reads of the finished ones."""
    inputs = None if index is None else plan.inputs(index, records)
    if inputs is None:
        return {}
    need = {inputs.previous: "full"}
    need.update({f: "tracks" for f in (inputs.earlier, inputs.earliest) if f is not None})
    return need


def pack_resume(run_dir: str | os.PathLike[str], out: str | os.PathLike[str], *,
                part_bytes: int = PART_BYTES, budget: int | None = None) -> dict:
    """Write what continues `run_dir` into `out` (module docstring); returns resume.json's
    content (`files`: every file written, resume.json last). Over `budget` bytes even with
    shN halved, the unfinished group's frames are left out (`dropped`: the next call makes
    them again) and only the records of whole groups are carried."""
    run, out = RunDir(run_dir), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("resume-*.npz"):
        old.unlink()
    resolved = run.read_run()
    plan, records, index = _next_frame(run, resolved)
    need = _needs(plan, records, index)
    arrays = {f: _arrays(run, f, kind) for f, kind in need.items()}
    lossy: dict[str, str] = {}
    raw = sum(a.nbytes for v in arrays.values() for a in v.values())
    if budget is not None and raw > budget:
        for v in arrays.values():
            if "shN" in v:
                v["shN"], lossy["shN"] = v["shN"].astype(np.float16), "float16"
    files = {f: _write_parts(out, f"resume-{_NAME.sub('_', f)}", a, part_bytes)
             for f, a in arrays.items()}
    static = run.static_seeds()
    static_files = _write_parts(out, STATIC_STEM, {"ply": np.frombuffer(
        static.read_bytes(), np.uint8)}, part_bytes) if static.is_file() else []
    total = sum((out / n).stat().st_size for names in files.values() for n in names)
    dropped: list[str] = []
    if budget is not None and total > budget:  # carry whole groups only
        group = plan.roles[index].gop
        dropped = [r.frame for r in plan.roles if r.gop == group and r.frame in records]
        records = {f: r for f, r in records.items() if f not in dropped}
        for names in files.values():
            for n in names:
                (out / n).unlink()
        need, files, lossy = {}, {}, {}
    metrics = {**run.read_metrics(), "frames": records}
    record = {"version": 1, "config": resolved.to_json(), "metrics": metrics,
              "sequence": plan.record(records), "carried": sorted(records),
              "next": dropped[0] if dropped else
              None if index is None else plan.roles[index].frame, "dropped": dropped,
              # The first frame the next call's capture must hold: a tracked frame reads its
              # previous frame's views too (the subject hull of a scene).
              "capture_from": next((f for f, kind in need.items() if kind == "full"), None)
              or (dropped[0] if dropped else None if index is None
                  else plan.roles[index].frame),
              "arrays": {f: {"kind": need[f], "files": files[f]} for f in need},
              "lossy": lossy, "static": static_files}
    (out / "resume.json").write_text(json.dumps(record))
    record["files"] = [n for names in files.values() for n in names] + static_files + \
        ["resume.json"]
    return record


def _load_parts(folder: Path, names: list[str]) -> dict[str, np.ndarray]:
    parts = []
    for name in names:
        with np.load(folder / name, allow_pickle=False) as z:
            parts.append({k: z[k] for k in z.files})
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def unpack_resume(folder: str | os.PathLike[str], run_dir: str | os.PathLike[str]) -> dict:
    """Lay out `pack_resume`'s files in `folder` as the run directory `run_dir` (new or empty),
    for `reconstruct(..., resume=True)`; returns resume.json's content."""
    folder, run = Path(folder), RunDir(run_dir)
    path = folder / "resume.json"
    if not path.is_file():
        raise ValueError(f"resume: {folder.name} has no resume.json (the files of a previous "
                         "call's pack_resume)")
    record = json.loads(path.read_text())
    if record.get("version") != 1:
        raise ValueError(f"resume: {path.name} is version {record.get('version')}, expected 1")
    run.check_new_or_resumable(False)
    run.write("config.json", record["config"])
    run.write("metrics.json", record["metrics"])
    if record.get("sequence") is not None:
        run.write("sequence.json", record["sequence"])
    run.write("carried.json", {"frames": record["carried"]})
    for frame, entry in record["arrays"].items():
        arrays = _load_parts(folder, entry["files"])
        run.frame_dir(frame).mkdir(parents=True, exist_ok=True)
        if entry["kind"] == "tracks":
            np.savez(run.frame_dir(frame) / "tracks.npz", ids=arrays["ids"],
                     means=arrays["means"])
        else:
            ids = arrays.pop("ids")
            write_gaussian_ply(run.ply(frame), {k: v.astype(np.float32)
                                                for k, v in arrays.items()}, ids)
    if record.get("static"):
        run.static_seeds().parent.mkdir(parents=True, exist_ok=True)
        run.static_seeds().write_bytes(_load_parts(folder, record["static"])["ply"].tobytes())
    return record


class FrameBudget:
    """Stops a run at a frame boundary when the next frame would not end before `deadline`
    (time.monotonic()) with `reserve()` seconds left over: each frame's seconds are predicted
    by the mean of its kind so far. Before a frame of the next one's kind has been measured
    nothing is planned (a guess would stop a run after its first key frame); then only the
    deadline itself stops it, inside the frame."""

    def __init__(self, gop: int, deadline: float | None,
                 reserve: Callable[[FrameBudget], float] = lambda budget: 0.0):
        self.gop, self.deadline, self.reserve = gop, deadline, reserve
        self.seconds: dict[str, list[float]] = {"key": [], "tracked": []}
        self.last, self.stop = time.monotonic(), False

    def predict(self, kind: str) -> float | None:
        """Mean seconds of the frames of `kind` ("key", "tracked") so far; None before one."""
        done = self.seconds[kind]
        return sum(done) / len(done) if done else None

    def on_progress(self, event) -> None:
        """Hand it `reconstruct`'s progress events (`core.pipeline.Progress`)."""
        if event.kind != "frame_done":
            return
        now = time.monotonic()
        kind = "key" if event.frame_index % self.gop == 0 else "tracked"
        self.seconds[kind].append(now - self.last)
        self.last = now
        following = self.predict("key" if (event.frame_index + 1) % self.gop == 0
                                 else "tracked")
        self.stop = self.deadline is not None and following is not None and \
            now + following + self.reserve(self) > self.deadline

    def should_stop(self) -> bool:
        """Asked after every step: at the planned boundary, or inside a frame that overran."""
        return self.stop or (self.deadline is not None and time.monotonic() > self.deadline)
