"""`ResolvedRun`: what a run was asked to do, resolved once (docs/design.md 2.3, 3.3, 3.6).

It is made once, by `resolve_run`: at the command line (`dgs reconstruct`) or at the door of
the service (`POST /v1/jobs`, which stores it with the job), from the preset, the overrides and
the capture. The worker runs the stored one without resolving anything again; RUN/config.json is
it serialized (`to_json`), and every stage after training (evaluation, meshes, relighting,
exports) loads it back typed with `read_run`, the one reader of config.json, which also
upgrades the records older versions wrote (`upgrade`).

Torch-free: the API process resolves and checks a job's run with it.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field

from core.config.base import ConfigError, section, validate
from core.config.run import RunConfig, load_config, parse_frames
from core.config.train import Preset
from core.config.views import Views, select_views
from core.data.capture import Capture
from core.data.layout import near_plane
from core.data.schema import load_capture

__all__ = ["CONFIG_VERSION", "ResolvedRun", "read_run", "resolve_run", "upgrade"]

CONFIG_VERSION = 5
"""The version of RUN/config.json this code writes (1: the configuration's fields at the top
level, without the resolved views; 2: no train.near, every render clipped at 0.01; 3: no
train.schedule.densify_epoch; 4: no train.losses.normal_confidence)."""

OLD_NEAR = 0.01
"""The near plane every render had before runs recorded theirs (the rasterizer's default)."""


@section
class ResolvedRun:
    """A run resolved against its capture: RUN/config.json's content."""

    preset: Preset
    """The preset the configuration started from."""
    capture: Annotated[str, Field(min_length=1, max_length=4096)]
    """The capture: its folder (command line) or its id (service; no record names a folder
    of the server)."""
    frames: Annotated[tuple[str, ...], Field(min_length=1)]
    """The frames to reconstruct, in order."""
    config: RunConfig
    """The resolved configuration (train.device as resolved where the run trained)."""
    views: Views
    """The views it trains on and scores, resolved against the capture."""

    def to_json(self) -> dict[str, Any]:
        """RUN/config.json's content (the job store keeps the same)."""
        data = json.loads(json.dumps(dataclasses.asdict(self)))
        return {"version": CONFIG_VERSION, **data}

    @classmethod
    def from_json(cls, data: Any, capture_dir: str | os.PathLike[str] | None = None,
                  where: str = "config.json") -> ResolvedRun:
        """The run a record of any version describes (`upgrade`); ConfigError naming each bad
        field under `where`."""
        current = dict(upgrade(data, capture_dir))
        current.pop("version")
        return validate(cls, current, where)

    def on_device(self, device: str) -> ResolvedRun:
        """This run with train.device `device` (where it trains; not part of what it is)."""
        train = dataclasses.replace(self.config.train, device=device)
        return dataclasses.replace(self, config=dataclasses.replace(self.config, train=train))

    def same_run(self, other: ResolvedRun) -> bool:
        """Whether `other` is this run (a resume must be): the same configuration and views,
        wherever each trains (a checkpoint holds CPU tensors); the frames may differ (a
        resume may add some)."""
        return (self.on_device("cpu").config, self.views) == (other.on_device("cpu").config,
                                                              other.views)


def _has_masks(capture: Capture, frames: list[str]) -> bool:
    return any(capture.mask_path(f, c.id) is not None for f in frames for c in capture.cameras)


def resolve_run(capture: Capture, config: RunConfig, *, preset: str, frames: str | None = None,
                capture_name: str | None = None, has_masks: bool | None = None) -> ResolvedRun:
    """The run of `config` on `capture`: the frames `frames` selects ('A:B', None: all), its
    views (`core.config.views.select_views`). ConfigError naming the setting (`frames`,
    `config.split`, `config.mesh.subject`) when the capture cannot run it: refused before
    anything is written or queued. `has_masks`: whether the capture has masks (None: look at
    the selected frames' files; the API, which never opens a capture's files, knows it from
    the commit's summary). `capture_name`: how the record names the capture (default: its
    folder)."""
    try:
        chosen = parse_frames(frames, capture.frames)
    except ValueError as exc:
        raise ConfigError([{"path": "frames", "message": str(exc).removeprefix(
            "frames: ")}]) from None
    try:
        views = select_views(capture, config.split, config.downscale, config.train.masks)
    except ConfigError as exc:
        raise ConfigError([{**d, "path": f"config.{d['path']}"} for d in exc.details]) from None
    if config.mesh.subject and not (_has_masks(capture, chosen) if has_masks is None
                                    else has_masks):
        raise ConfigError([{"path": "config.mesh.subject", "message": (
            "the capture has no masks, so nothing says where the subject is; mesh the whole "
            "scene (mesh.subject false)")}])
    if config.train.near is None:
        train = dataclasses.replace(config.train, near=near_plane(capture.cameras))
        config = dataclasses.replace(config, train=train)
    return ResolvedRun(preset, capture_name or str(capture.root.resolve()),  # type: ignore
                       tuple(chosen), config, views)


def upgrade(data: Any, capture_dir: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """A RUN/config.json record of any version as the current version's JSON; the one place
    old records are read. Version 1 (the configuration's fields at the top level) gets its
    views resolved against its capture (`capture_dir`, else the folder it names): the same
    rule its run followed. Versions 1 and 2 get train.near 0.01, the plane they rendered at;
    versions 1 to 3 train.schedule.densify_epoch false, the interval they densified at;
    versions 1 to 4 train.losses.normal_confidence `per_view`, how their priors' confidences
    weighed."""
    if not isinstance(data, dict):
        raise ConfigError([{"path": "config.json", "message": "expected a JSON object"}])
    version = data.get("version")
    if version == CONFIG_VERSION:
        return data
    if version not in (1, 2, 3, 4):
        raise ConfigError([{"path": "config.json", "message": f"version {version!r} is not "
                            f"one this code reads (1 to {CONFIG_VERSION})"}])
    record = _from_version_1(data, capture_dir) if version == 1 else data
    config = record.get("config")
    train = config.get("train") if isinstance(config, dict) else None
    if isinstance(train, dict):
        if version < 3 and train.get("near") is None:
            train = {**train, "near": OLD_NEAR}
        schedule = train.get("schedule")
        if version < 4 and isinstance(schedule, dict):  # (version 1's: today's defaults)
            train = {**train, "schedule": {**schedule, "densify_epoch": False}}
        losses = train.get("losses")
        if isinstance(losses, dict):
            train = {**train, "losses": {**losses, "normal_confidence": "per_view"}}
        record = {**record, "config": {**config, "train": train}}
    return {**record, "version": CONFIG_VERSION}


def _from_version_1(data: dict[str, Any], capture_dir) -> dict[str, Any]:
    keys = [f.name for f in dataclasses.fields(RunConfig)]
    config = load_config(data.get("preset", "fast"), overrides={
        k: data[k] for k in keys if k in data}, where="config.json")
    folder = Path(capture_dir if capture_dir is not None else str(data.get("capture", "")))
    if not (folder / "capture.json").is_file():
        raise ValueError("capture: config.json is a version 1 record, whose views are resolved "
                         "against its capture; pass the capture folder (--capture)")
    views = select_views(load_capture(folder), config.split, config.downscale,
                         config.train.masks)
    return {"version": 1, "preset": data.get("preset", "fast"),
            "capture": data.get("capture"), "frames": data.get("frames"),
            "config": dataclasses.asdict(config), "views": dataclasses.asdict(views)}


def read_run(run_dir: str | os.PathLike[str],
             capture_dir: str | os.PathLike[str] | None = None) -> ResolvedRun:
    """RUN/config.json as the `ResolvedRun` it records (of any version, `upgrade`); ValueError
    when `run_dir` is not a run directory."""
    path = Path(run_dir) / "config.json"
    if not path.is_file():
        raise ValueError(f"run_dir: {Path(run_dir).name} is not a run directory (no "
                         "config.json)")
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"run_dir: config.json is not JSON ({exc})") from None
    return ResolvedRun.from_json(data, capture_dir)
