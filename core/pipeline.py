"""The main job: reconstruct every selected frame of a capture into a run directory (DESIGN.md 3.3).

Per frame: the full static stages (`core.train.Trainer`), a PLY, renders of the held-out cameras,
per-frame metrics; checkpoints land atomically under RUN/checkpoints/<frame>.pt so an interrupted
run resumes where it stopped. Frames are grouped into GoPs (`gop`, DESIGN.md section 5): the first
frame of each group gets the full static stages, the others are deformed from their predecessor
and refined (`core.sequence`); RUN/sequence.json records groups, roles, timings and counts.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from core.sequence.budget import median_deform_loss, refine_credit
from core.sequence.config import SequenceConfig
from core.progress import LogLines, TerminalBar, frame_iterations
from core.train import Callback, CheckpointCallback, StepInfo, TrainConfig, Trainer, train_config

__all__ = ["Progress", "RunConfig", "RunMesh", "Stopped", "apply_overrides", "parse_frames", "reconstruct",
           "render_heldout", "resolve_config", "write_json"]

# Geometry coverage above which a pixel gets a normal and AO in the pictures (else black): low
# enough that the soft edges of a short run still show, high enough that the direction of the
# alpha-weighted normal sum is not noise.
COVERAGE = 0.2

SEQUENCE_NOTE = ("the first frame of each GoP is reconstructed with the full static stages, the "
                 "others deformed from the previous frame and refined (see sequence.json)")
INDEPENDENT_NOTE = ("sequence.enabled is off: every frame was reconstructed independently with the "
                    "full static stages")


@dataclass(frozen=True)
class Progress:
    """One event of a running reconstruction, for `reconstruct(on_progress=...)`."""

    kind: Literal["frame_start", "step", "checkpoint", "frame_done"]
    """What happened: a frame starts (or resumes), a step ended, a checkpoint is complete on disk
    (`path`), a frame's outputs are written."""
    frame: str
    """The frame's name."""
    frame_index: int
    """Its position among the selected frames (0-based)."""
    frames: int
    """How many frames the run has."""
    step: int
    """Steps of this frame done so far (after the step for kind 'step')."""
    iterations: int
    """Steps per frame."""
    stage: int
    """Training stage of the last step (1, 2, 3; 0 before the first)."""
    gaussians: int = 0
    """Gaussians in the model."""
    loss: float | None = None
    """Total loss of the step (kind 'step')."""
    path: str | None = None
    """The checkpoint file (kind 'checkpoint') or the frame's folder (kind 'frame_done')."""
    phase: Literal["key", "deform", "refine"] = "key"
    """How the frame is made: static stages (a GoP's key frame), or the deform / refine stage
    of a frame deformed from its predecessor."""
    notes: tuple[str, ...] = ()
    """kind 'frame_start': what the trainer noted while it was made (where its initial points
    came from, a fallback to random points), for the job's log."""


class Stopped(Exception):
    """`reconstruct` stopped because `should_stop()` said so; the frame's checkpoint was written
    first, so `resume=True` continues from the step it stopped at."""

    def __init__(self, frame: str, step: int):
        super().__init__(f"stopped at step {step} of frame {frame} (checkpoint written)")
        self.frame, self.step = frame, step


@dataclass(frozen=True)
class RunMesh:
    """The meshes `reconstruct` writes for every finished frame (RUN/meshes/<frame>.<fmt>, TSDF
    of the geometry branch, DESIGN.md section 5; `dgs mesh` makes others afterwards)."""

    enabled: bool = True
    """Mesh each frame as soon as it is finished."""
    resolution: int = 512
    """Voxels along the scene diagonal (DESIGN.md: 512)."""
    formats: str = "ply"
    """Comma-separated file formats: any of ply, obj, glb."""

    def config(self):
        """The `core.mesh.MeshConfig` these settings stand for (ValueError when invalid)."""
        from core.mesh import MeshConfig

        return MeshConfig(resolution=self.resolution,
                          formats=tuple(f.strip() for f in self.formats.split(",") if f.strip()))

    def __post_init__(self) -> None:
        self.config()


@dataclass(frozen=True)
class RunConfig:
    """What a run needs beyond one frame's training configuration."""

    train: TrainConfig = field(default_factory=TrainConfig)
    """How each frame is trained (the preset, with overrides applied)."""
    checkpoint_every: int = 1000
    """Steps between checkpoints (RUN/checkpoints/<frame>.pt, written atomically)."""
    gop: int = 20
    """Frames per group of pictures: the first gets the static stages, the others deform +
    refine (DESIGN.md section 5)."""
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    """How the frames after a group's first are deformed and refined."""
    normal_estimator: str | None = None
    """Model file (TorchScript, or .onnx with onnxruntime) for views without a normals/ prior."""
    normal_estimator_space: str = "camera"
    """'camera' or 'world': the space the estimator's normals are in."""
    downscale: float = 1.0
    """Train on the images reduced by this factor (area averaging, intrinsics scaled); held-out
    views are rendered and scored at the same reduced size (as papers do with images_4)."""
    mesh: RunMesh = field(default_factory=RunMesh)
    """Meshes written with every finished frame."""

    def __post_init__(self) -> None:
        if not self.downscale >= 1.0:
            raise ValueError(f"downscale: expected a factor >= 1, got {self.downscale}")
        if self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every: expected >= 1, got {self.checkpoint_every}")
        if self.gop < 1:
            raise ValueError(f"gop: expected >= 1, got {self.gop}")
        if self.normal_estimator_space not in ("camera", "world"):
            raise ValueError("normal_estimator_space: expected 'camera' or 'world', got "
                             f"{self.normal_estimator_space!r}")


def _convert(current: object, value: object, where: str, annotation: str = "") -> object:
    """`value` from JSON in the type of `current` (tuples from lists, floats from ints); for an
    optional field (`annotation` such as 'int | None'), None or a value of the named type; a
    field annotated `tuple[T, ...]` takes a list of any length (empty included)."""
    optional = annotation.replace(" ", "").endswith("|None")
    if optional and value is None:
        return None
    if optional and current is None:  # judge by the annotation's type instead
        current = {"int": 0, "float": 0.0, "bool": False}.get(annotation.split("|")[0].strip(),
                                                                "")
    if isinstance(current, bool) or isinstance(value, bool):
        ok = isinstance(current, bool) and isinstance(value, bool)
    elif isinstance(current, int):
        ok = isinstance(value, int)
    elif isinstance(current, float):
        ok, value = isinstance(value, (int, float)), float(value) if isinstance(
            value, (int, float)) else value
    elif isinstance(current, tuple) and annotation.replace(" ", "").endswith(",...]"):
        like = {"int": 0, "float": 0.0, "bool": False}.get(
            annotation.split("[", 1)[1].split(",")[0].strip(), "")
        ok = isinstance(value, list)
        value = tuple(_convert(like, v, f"{where}[{i}]") for i, v in enumerate(value)) \
            if ok else value
    elif isinstance(current, tuple):
        ok = isinstance(value, list) and len(value) == len(current)
        value = tuple(_convert(c, v, where) for c, v in zip(current, value)) if ok else value
    else:  # str | None fields
        ok = value is None or isinstance(value, str)
    if not ok:
        raise ValueError(f"{where}: expected a value like {current!r}, got {value!r}")
    return value


def apply_overrides(obj, overrides: dict, where: str = "config"):
    """A copy of dataclass `obj` with the (nested) JSON `overrides` applied; unknown keys and
    wrong types raise ValueError naming the key."""
    if not isinstance(overrides, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(overrides).__name__}")
    names = {f.name: str(f.type) for f in fields(obj)}  # annotations are strings here
    changes = {}
    for key, value in overrides.items():
        if key not in names:
            raise ValueError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(names))})")
        current = getattr(obj, key)
        if is_dataclass(current):
            changes[key] = apply_overrides(current, value, f"{where}.{key}")
        else:
            changes[key] = _convert(current, value, f"{where}.{key}", names[key])
    try:
        return replace(obj, **changes)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def resolve_config(preset: str, config_file: str | os.PathLike[str] | None = None) -> RunConfig:
    """The preset's configuration with a JSON file's overrides (same shape as RUN/config.json's
    `train`, `checkpoint_every`, ... keys)."""
    test = preset == "test"
    # The test preset's tiny captures mesh at 128 voxels along the diagonal (about a second a
    # frame on a CPU instead of 15).
    cfg = RunConfig(train=train_config(preset), checkpoint_every=100 if test else 1000,
                    mesh=RunMesh(resolution=128) if test else RunMesh())
    if config_file is None:
        return cfg
    path = Path(config_file)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"config: cannot read {path}: {exc}") from None
    return apply_overrides(cfg, data, where=str(path))


def parse_frames(spec: str | None, frames: tuple[str, ...] | list[str]) -> list[str]:
    """`A:B` (a Python slice, also `A:`, `:B`, `A:B:S` or a single index) over the capture's
    frame list; None selects every frame."""
    if spec is None:
        return list(frames)
    try:
        parts = [int(p) if p.strip() else None for p in str(spec).split(":")]
        if len(parts) > 3:
            raise ValueError
        chosen = (list(frames)[slice(*parts)] if len(parts) > 1
                  else [list(frames)[parts[0]]])
    except (ValueError, IndexError):
        raise ValueError(f"frames: expected A:B (a slice over {len(frames)} frames), "
                         f"got {spec!r}") from None
    if not chosen:
        raise ValueError(f"frames: {spec!r} selects no frame of the {len(frames)} in the capture")
    return chosen


def write_json(path: Path, data) -> None:
    """Write JSON atomically (a reader never sees half a file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)


class _History(Callback):
    """Per-step records for metrics.json and the plots (survives resume via the checkpoint)."""

    def __init__(self) -> None:
        self.records: list[dict] = []

    def on_step_end(self, trainer: Trainer, info: StepInfo) -> None:
        self.records.append({"step": info.step, "stage": info.plan.stage,
                             "gaussians": info.n_gaussians, "psnr": info.psnr,
                             "seconds": info.seconds, **info.losses})


class _Hooks(Callback):
    """Hands `Progress` events to the caller and stops (after a checkpoint) when asked to."""

    def __init__(self, frame: str, index: int, frames: int,
                 on_progress: Callable[[Progress], None] | None,
                 should_stop: Callable[[], bool] | None):
        self.frame, self.index, self.frames = frame, index, frames
        self.on_progress, self.should_stop = on_progress, should_stop
        self.saver: CheckpointCallback | None = None
        self.trainer: Trainer | None = None
        self.stage = 0
        self.loss: float | None = None

    def emit(self, kind: str, trainer: Trainer | None, path: str | None = None) -> None:
        trainer = trainer or self.trainer
        if self.on_progress is None or trainer is None:
            return
        self.on_progress(Progress(
            kind=kind, frame=self.frame, frame_index=self.index, frames=self.frames,
            step=trainer.step, iterations=frame_iterations(trainer), stage=self.stage,
            gaussians=len(trainer.model), loss=self.loss if kind == "step" else None, path=path,
            phase=getattr(trainer, "phase", "key"),
            notes=tuple(trainer.notes) if kind == "frame_start" else ()))

    def on_train_start(self, trainer: Trainer) -> None:
        self.trainer = trainer
        self.emit("frame_start", trainer)

    def on_step_end(self, trainer: Trainer, info: StepInfo) -> None:
        self.stage, self.loss = info.plan.stage, info.losses["total"]
        self.emit("step", trainer)
        last = trainer.step >= frame_iterations(trainer)
        if self.should_stop is not None and not last and self.should_stop():
            if self.saver is not None:
                self.saver.save(trainer)
            raise Stopped(self.frame, trainer.step)


def _check_run_dir(run: Path, resume: bool) -> None:
    if not run.exists() or (run.is_dir() and not any(run.iterdir())):
        return
    if not run.is_dir():
        raise ValueError(f"out: {run} exists and is not a folder")
    if not resume:
        raise ValueError(f"out: {run} already exists and is not empty; pass --resume to continue "
                         "a run there, or choose another folder")
    if not (run / "config.json").is_file():
        raise ValueError(f"out: {run} is not a run directory (no config.json); cannot resume")


def _config_record(capture_dir: Path, preset: str, chosen: list[str], cfg: RunConfig) -> dict:
    return {"version": 1, "preset": preset, "capture": str(capture_dir.resolve()),
            "frames": chosen, **asdict(cfg)}


def _same_config(old: dict, new: dict) -> bool:
    """Whether two config.json records describe the same run. The device is left out: a run
    resumes on another machine (a checkpoint holds CPU tensors), and records written before
    the field existed have none."""
    keys = [f.name for f in fields(RunConfig)]

    def comparable(record: dict) -> dict:
        data = json.loads(json.dumps({k: record.get(k) for k in keys}))
        if isinstance(data.get("train"), dict):
            data["train"].pop("device", None)
        return data

    return comparable(old) == comparable(new)


def _resolve_run_device(cfg: RunConfig, device: str | None) -> RunConfig:
    """`cfg` with `device` (when given) and then the device it stands for written into
    train.device (`auto` becomes `cuda:0` or `cpu`), so that config.json says where the run
    trained; ValueError (before anything is written) when CUDA is asked for and not usable."""
    from core.device import check_device_spec, resolve_device

    where = "device" if device is not None else "train.device"
    spec = check_device_spec(device, where) if device is not None else cfg.train.device
    resolved = resolve_device(spec, where)
    return replace(cfg, train=replace(cfg.train, device=str(resolved)))


def reconstruct(capture_dir: str | os.PathLike[str], run_dir: str | os.PathLike[str], *,
                preset: str = "fast", frames: str | None = None,
                config_file: str | os.PathLike[str] | None = None, resume: bool = False,
                gop: int | None = None, overrides: dict | None = None,
                progress: bool = True, on_progress: Callable[[Progress], None] | None = None,
                should_stop: Callable[[], bool] | None = None, device: str | None = None) -> dict:
    """Reconstruct the selected frames (`frames`: 'A:B' over the capture's frame list) into
    `run_dir`; returns the metrics (also RUN/metrics.json). `resume` continues an interrupted
    run: finished frames are skipped, an unfinished one restarts from its checkpoint. `gop`
    overrides the configuration's group-of-pictures length (the first frame of each group is a key frame);
    `overrides` (same shape as a --config file) apply after the file. `device` (auto, cpu, cuda,
    cuda:N) overrides train.device; RUN/config.json records the device it resolved to.

    `progress` shows a bar on a terminal; `on_progress` receives `Progress` events (every step,
    checkpoint and frame); `should_stop` is asked after every step and, when it returns True,
    the frame's checkpoint is written and `Stopped` raised (a service's cooperative cancel)."""
    from core.data import check_capture

    capture_dir, run = Path(capture_dir), Path(run_dir)
    cfg = resolve_config(preset, config_file)
    if overrides:
        cfg = apply_overrides(cfg, overrides, where="overrides")
    if gop is not None:
        cfg = replace(cfg, gop=gop)
    cfg = _resolve_run_device(cfg, device)
    from core.priors import load_estimator

    # Every input is checked before anything is written, so bad input leaves no half run behind.
    estimator = load_estimator(cfg.normal_estimator, cfg.normal_estimator_space)
    capture = check_capture(capture_dir)
    chosen = parse_frames(frames, capture.frames)
    _check_run_dir(run, resume)
    record = _config_record(capture_dir, preset, chosen, cfg)
    if (run / "config.json").is_file():
        old = json.loads((run / "config.json").read_text())
        if not _same_config(old, record):
            raise ValueError(f"resume: {run / 'config.json'} records another configuration; "
                             "resume with the same --preset and --config")
    write_json(run / "config.json", record)
    metrics_path = run / "metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {}
    metrics.update({"version": 1, "preset": preset, "gop": cfg.gop,
                    "note": SEQUENCE_NOTE if cfg.sequence.enabled else INDEPENDENT_NOTE})
    metrics.setdefault("frames", {})
    # A bar on a terminal; elsewhere (a log, nohup) a line every 30 s, so long runs never go quiet.
    display = None if not progress else "bar" if sys.stderr.isatty() else "lines"
    from core.sequence.gop import roles
    from core.sequence.run import sequence_record

    planned = roles(chosen, cfg.gop if cfg.sequence.enabled else 1)
    nominal = cfg.sequence.steps(cfg.train.schedule.iterations)[1]
    for i, role in enumerate(planned):
        frame = role.frame
        if frame in metrics["frames"] and (run / "frames" / frame / "gaussians.ply").is_file():
            continue
        label = f"frame {frame} ({i + 1}/{len(chosen)})"
        hooks = _Hooks(frame, i, len(chosen), on_progress, should_stop)
        before = None if role.key else metrics["frames"][role.previous]
        # The previous frame's deform loss; None after a key frame (a group's second frame).
        reference = None if before is None else before.get("deform_loss")
        ahead = min(cfg.sequence.refine_borrow, sum(not r.key for r in planned[i + 1:]))
        credit = refine_credit(metrics["frames"], ahead, nominal,
                               cfg.sequence.refine_floor(nominal))
        metrics["frames"][frame] = {**_reconstruct_frame(
            capture, frame, run, cfg, estimator, (label, display), hooks,
            previous=role.previous, next_id=None if before is None else before["next_track_id"],
            reference_loss=reference,
            earlier=None if before is None else before.get("previous"),
            earliest=None if not before or not before.get("previous") else
            metrics["frames"][before["previous"]].get("previous"),
            refine_credit=credit,
            refine_reference=None if before is None or reference is not None
            else median_deform_loss(metrics["frames"])),
            "gop": role.gop, "position": role.position}
        if metrics["frames"][frame]["rekeyed"]:  # a key frame now (sequence.json: a new group)
            metrics["frames"][frame]["position"] = 0
        write_json(metrics_path, metrics)
        write_json(run / "sequence.json",
                   sequence_record(chosen, cfg.gop, cfg.sequence, metrics["frames"]))
        hooks.emit("frame_done", None, path=str(run / "frames" / frame))
        # The frame is finished (PLY and metrics on disk): its training state is no longer needed.
        (run / "checkpoints" / f"{frame}.pt").unlink(missing_ok=True)
        (run / "checkpoints" / f"{frame}.rekey.json").unlink(missing_ok=True)
    from core.plots import plot_run

    plot_run(run)
    return metrics


def _reconstruct_frame(capture, frame: str, run: Path, cfg: RunConfig, estimator,
                       shown: tuple[str, str | None], hooks: _Hooks, previous: str | None = None,
                       next_id: int | None = None, reference_loss: float | None = None,
                       earlier: str | None = None, refine_credit: int = 0,
                       refine_reference: float | None = None,
                       earliest: str | None = None) -> dict:
    """A key frame (`previous` None) with the static stages, or a frame deformed from
    `previous` (whose own predecessors in the group, `earlier` and `earliest`, give the motion
    to continue)
    and refined; `next_id` is its group's next unused track id, `refine_credit` the refine
    steps it may run beyond the nominal (`refine_credit()`)."""
    from core.priors import fill_priors
    from core.sequence.run import save_frame, tracker_from_capture

    history = _History()
    ckpt_dir = run / "checkpoints"
    saver = CheckpointCallback(ckpt_dir, cfg.checkpoint_every, filename=f"{frame}.pt",
                               extra=lambda: history.records,
                               on_saved=lambda path: hooks.emit("checkpoint", None, path=str(path)))
    hooks.saver = saver
    callbacks: list[Callback] = [history, saver]
    label, display = shown
    if display is not None:
        callbacks.append(TerminalBar(label) if display == "bar" else LogLines(label))
    callbacks.append(hooks)  # last: a stop sees the step's history and checkpoint
    start = time.perf_counter()
    ckpt = ckpt_dir / f"{frame}.pt"
    rekey_path = ckpt_dir / f"{frame}.rekey.json"
    rekeyed = json.loads(rekey_path.read_text()) if rekey_path.is_file() else None
    if rekeyed is not None:  # a re-keyed frame resumed: its checkpoint is the key frame's
        previous = None

    def key_trainer() -> Trainer:
        return Trainer.from_capture(capture, frame, cfg.train, callbacks=callbacks,
                                    downscale=cfg.downscale)

    if previous is None:
        trainer = key_trainer()
    else:
        trainer = tracker_from_capture(capture, frame, run / "frames" / previous / "gaussians.ply",
                                       next_id, cfg.train, cfg.sequence, downscale=cfg.downscale,
                                       callbacks=callbacks, reference_loss=reference_loss,
                                       refine_credit=refine_credit,
                                       refine_reference=refine_reference,
                                       earlier_ply=None if earlier is None
                                       else run / "frames" / earlier / "gaussians.ply",
                                       earliest_ply=None if earliest is None
                                       else run / "frames" / earliest / "gaussians.ply")
    priors = fill_priors(trainer.views, estimator)
    resumed_at = 0
    if ckpt.is_file():
        history.records = list(trainer.load_checkpoint(ckpt) or [])
        resumed_at = trainer.step
    trainer.train()
    if previous is not None and trainer.lost_track is not None:
        # Tracking lost (`SequenceConfig.rekey_loss_ratio`): the frame becomes a key frame.
        rekeyed = {"from": previous, "loss_ratio": round(trainer.lost_track, 4),
                   "tracked_renders": trainer.renders_done, "deform_loss": trainer.deform_loss}
        write_json(rekey_path, rekeyed)
        ckpt.unlink(missing_ok=True)
        history.records = []
        previous = None
        trainer = key_trainer()
        priors = fill_priors(trainer.views, estimator)
        trainer.train()
    out = run / "frames" / frame
    out.mkdir(parents=True, exist_ok=True)
    ids = None if previous is None else trainer.ids
    save_frame(out / "gaussians.ply", trainer.model, ids)
    render_heldout(capture, frame, trainer, run / "renders" / frame, cfg.downscale)
    mesh = _mesh_frame(run, capture, frame, cfg.mesh)
    last = history.records[-1] if history.records else {}
    return {
        "iterations": frame_iterations(trainer),
        "renders": (getattr(trainer, "renders", None) or frame_iterations(trainer))
        + (rekeyed["tracked_renders"] if rekeyed else 0),
        "seconds": round(time.perf_counter() - start, 3),
        "ao_bake_seconds": None if getattr(trainer, "ao_seconds", None) is None
        else round(trainer.ao_seconds, 3),
        "resumed_at": resumed_at,
        "gaussians": len(trainer.model),
        "final_losses": {k: v for k, v in last.items()
                         if k not in ("step", "stage", "gaussians", "psnr", "seconds")},
        "train_psnr": round(trainer.evaluate(), 4),
        "normal_prior": priors,
        "stages": "static (key frame)" if previous is None else "deform + refine",
        "rekeyed": rekeyed,
        "previous": previous,
        "next_track_id": len(trainer.model) if previous is None else trainer.group_next_id,
        "new_tracks": None if previous is None else trainer.state.born,
        "start": None if previous is None else {"from": trainer.start,
                                                "scores": dict(trainer.race.scores),
                                                "views": dict(trainer.race.views)},
        "deform_loss": getattr(trainer, "deform_loss", None),
        "refine_steps": None if previous is None else trainer.refine_steps,
        "refine_nominal": None if previous is None else trainer.nominal_refine,
        # Renders the start race took beyond `start_views`, paid from the refine steps.
        "scoring_extra": None if previous is None else trainer.scoring_extra,
        "deform_rounds": None if previous is None else [r[0] for r in trainer.rounds.ended],
        "notes": trainer.notes,
        "mesh": mesh,
        "history": _thin(history.records),
    }


def _mesh_frame(run: Path, capture, frame: str, settings: RunMesh) -> dict | None:
    """RUN/meshes/<frame>.<fmt> (kept when a resumed run already wrote them); its statistics, or
    {"error": ...} when the frame has no surface to mesh (the run goes on)."""
    if not settings.enabled:
        return None
    from core.mesh import mesh_run

    result = mesh_run(run, frames=[frame], config=settings.config(), capture_dir=capture.root,
                      skip_existing=True, errors="record")
    return result["frames"].get(frame)


def _thin(records: list[dict], keep: int = 2000) -> list[dict]:
    """At most about `keep` records (every k-th and the last) so metrics.json stays small."""
    k = max(1, -(-len(records) // keep))
    out = records[::k]
    if records and out[-1] is not records[-1]:
        out.append(records[-1])
    return [{key: (round(v, 6) if isinstance(v, float) else v) for key, v in r.items()}
            for r in out]


@torch.no_grad()
def render_heldout(capture, frame: str, trainer: Trainer, out: Path,
                   downscale: float = 1.0) -> list[str]:
    """Write <camera>_rgb.png, _normal.png, _ao.png and _depth.npy for the held-out cameras
    (index % 8 == 0) at the training resolution (the input reduced by `downscale`); returns
    their ids."""
    from core.data.dataset import CaptureDataset
    from core.data.images import write_png
    from core.render import RenderCamera, render, safe_divide
    from core.stages import plan

    p = plan(trainer.config.schedule.iterations - 1, trainer.config.schedule)
    device = trainer.model.device
    bg = torch.tensor(trainer.config.background, dtype=torch.float32, device=device)
    ids = []
    served = CaptureDataset(capture, frames=[frame], downscale=downscale).served_camera
    for index, cam in enumerate(capture.cameras):
        if index % 8:
            continue
        r = render(trainer.model, RenderCamera.from_camera(served(cam), device=device),
                   sh_degree=p.sh_degree, beta=p.beta, geometry=True, tie_opacity=False,
                   background=bg, eps2d=trainer.config.eps2d,
                   antialiased=trainer.config.antialiased)
        rgb = r.rgb.clamp(0, 1).cpu().numpy()
        image = capture.image_path(frame, cam.id)
        if image is not None and image.suffix.lower() == ".exr":
            from core.synth.shading import linear_to_srgb  # the capture is linear: encode it

            rgb = linear_to_srgb(rgb)
        covered = (r.alpha_g > COVERAGE).cpu().numpy()
        # Training leaves the normal map unnormalized (DESIGN.md 5); the picture shows directions.
        n = torch.nn.functional.normalize(r.normal, dim=-1).cpu().numpy()
        ao = safe_divide(r.visibility, r.alpha_g).clamp(0, 1).cpu().numpy()
        to8 = lambda a: (np.clip(a, 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
        write_png(out / f"{cam.id}_rgb.png", to8(rgb))
        write_png(out / f"{cam.id}_normal.png", to8(np.where(covered, (n + 1) / 2, 0.0)))
        write_png(out / f"{cam.id}_ao.png", to8(np.where(covered, ao, 0.0)))
        np.save(out / f"{cam.id}_depth.npy", r.depth[..., 0].cpu().numpy().astype(np.float32))
        ids.append(cam.id)
    return ids
