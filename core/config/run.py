"""The whole run's configuration (`RunConfig`): presets, overrides from a JSON file or a request,
and the selection of frames. The CLI (`dgs reconstruct --config`) and the API (`POST /v1/jobs`)
both go through `load_config`, so a bad setting gets the same message in both."""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import field
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field

from core.config.base import ConfigError, Device, Fraction, section, validate
from core.config.sequence import SequenceConfig
from core.config.train import PRESETS, TrainConfig, train_config
from core.config.views import Split

__all__ = ["CheckpointEvery", "GopSize", "MESH_FORMATS", "MeshConfig", "RunConfig",
           "apply_overrides", "load_config", "parse_frames", "preset_config"]

MESH_FORMATS = ("ply", "obj", "glb")
GopSize = Annotated[int, Field(ge=1, le=10_000)]
"""Frames per group of pictures."""
CheckpointEvery = Annotated[int, Field(ge=1, le=1_000_000)]
"""Steps between checkpoints."""


@section
class MeshConfig:
    """How a frame is meshed (`core.mesh`): a TSDF of the geometry branch's depth."""

    enabled: bool = True
    """`dgs reconstruct`: mesh each frame as soon as it is finished."""
    resolution: Annotated[int, Field(ge=16, le=2048)] = 512
    """Voxels along the scene box's diagonal (voxel = diagonal / resolution)."""
    truncation_voxels: Annotated[float, Field(gt=0, le=100)] = 5.0
    """TSDF truncation distance in voxels."""
    alpha_threshold: Annotated[float, Field(gt=0, lt=1)] = 0.5
    """Pixels count as surface where the coverage is above this."""
    depth: Literal["geometry", "appearance"] = "geometry"
    """Which branch's depth is fused ('appearance' is the baseline)."""
    box: Literal["gaussians", "cameras"] = "gaussians"
    """Scene box: the opaque Gaussians' extent (0.5-99.5 percentiles of their means) or the
    ball every training camera sees around their look-at centre."""
    margin: Annotated[float, Field(ge=0, le=10)] = 0.05
    """Box padding as a fraction of its diagonal (plus the truncation distance)."""
    min_component: Fraction = 0.05
    """Connected components with fewer faces than this fraction of the largest are dropped."""
    colors: bool = True
    """Vertex colours from the appearance branch."""
    formats: Annotated[tuple[Literal["ply", "obj", "glb"], ...],
                       Field(min_length=1, max_length=3)] = ("ply",)
    """Files written per frame: any of ply, obj, glb."""
    chunk: Annotated[int, Field(ge=1024, le=1 << 26)] = 1 << 20
    """Voxels per vectorized TSDF step (memory bound of the temporaries)."""
    device: Device | None = None
    """Torch device of the TSDF; None: CUDA when available, else the CPU."""
    subject: bool = False
    """Mesh only the subject: the Gaussians inside the hull of the frame's subject masks
    (`core.sequence.hull`; the performers without the stage). The capture needs masks."""


@section
class RunConfig:
    """Everything a run needs: how each frame trains, and what the run does around it."""

    train: TrainConfig = field(default_factory=TrainConfig)
    """How each key frame is trained (the preset, with overrides applied)."""
    checkpoint_every: CheckpointEvery = 1000
    """Steps between checkpoints (RUN/checkpoints/<frame>.pt, written atomically)."""
    gop: GopSize = 20
    """Frames per group of pictures: the first is a key frame, the others deform + refine."""
    sequence: SequenceConfig = field(default_factory=SequenceConfig)
    """How the frames after a group's first are deformed and refined."""
    normal_estimator: Annotated[str, Field(min_length=1, max_length=4096)] | None = None
    """Normal-prior model for views without a normals/ prior: on the command line a file
    (TorchScript, or .onnx with onnxruntime); through the API an asset id or a name the
    operator allows."""
    normal_estimator_space: Literal["camera", "world"] = "camera"
    """The space the estimator's normals are in."""
    rig_priors: bool = True
    """Views with neither a normals/ prior nor an estimator get one from their key frame's
    fused stereo depth, with a confidence (`core.rig`); off: no prior there (the
    depth-normal consistency term alone shapes their normals)."""
    split: Split = "auto"
    """Which cameras are held out (`core.config.views`): `auto` the capture's declared
    test_cameras, else every 8th; `capture` the declared ones; `every8`; `none` (every camera
    trains; renders and metrics then on training views, labelled so)."""
    downscale: Annotated[float, Field(ge=1, le=64)] = 1.0
    """Train on the images reduced by this factor (area averaging, intrinsics scaled);
    held-out views are rendered and scored at the same size."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    """Meshes written with every finished frame."""


def preset_config(preset: str, method: str = "disentangled") -> RunConfig:
    """The named preset's run configuration (`paper`, `fast`, `test`) for `method`."""
    if preset not in PRESETS:
        raise ConfigError([{"path": "preset", "message": f"expected one of "
                            f"{', '.join(PRESETS)}, got {json.dumps(preset)}"}])
    train = train_config(preset, method)
    if preset == "test":
        # The test preset's tiny captures mesh at 128 voxels (a second a frame, not 15).
        return RunConfig(train=train, checkpoint_every=100, mesh=MeshConfig(resolution=128))
    return RunConfig(train=train)


def _merge(base: Any, over: Any) -> Any:
    """`over` laid on `base`: objects key by key (recursively), anything else replaced. Keys
    `base` lacks are kept, so that validation names them."""
    if not isinstance(base, dict) or not isinstance(over, dict):
        return over
    return {**base, **{k: _merge(base[k], v) if k in base else v for k, v in over.items()}}


def apply_overrides(cfg: Any, overrides: Any, where: str = "config") -> Any:
    """A copy of configuration section `cfg` with the (nested) JSON `overrides` laid on it;
    ConfigError naming each unknown key, wrong type or out-of-range value (paths under
    `where`)."""
    if not isinstance(overrides, dict):
        raise ConfigError([{"path": where, "message": "expected a JSON object, got "
                            f"{type(overrides).__name__}"}])
    return validate(type(cfg), _merge(dataclasses.asdict(cfg), overrides), where)


def load_config(preset: str = "fast", config_file: str | os.PathLike[str] | None = None,
                overrides: dict | None = None, *, gop: int | None = None,
                where: str = "config") -> RunConfig:
    """The preset's configuration, then a JSON file's overrides, then `overrides` (both in the
    shape of RUN/config.json's `config`), then `gop`; ConfigError on any bad setting. A
    `train.method` among them brings that method's defaults under every override
    (`method_defaults`): the preset's plan with 3DGS's densification, say, unless a setting
    names another value."""
    layers: list[tuple[dict, str]] = []
    if config_file is not None:
        path = Path(config_file)
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ConfigError([{"path": "config", "message": f"cannot read {path.name}: "
                                f"{exc}"}]) from None
        layers.append((data, path.name))
    if overrides:
        layers.append((overrides, where))
    if gop is not None:
        layers.append(({"gop": gop}, ""))
    cfg = preset_config(preset)
    for data, at in layers:
        cfg = apply_overrides(cfg, data, where=at)
    if cfg.train.method != "disentangled":  # again, on the method's defaults
        cfg = preset_config(preset, cfg.train.method)
        for data, at in layers:
            cfg = apply_overrides(cfg, data, where=at)
    return cfg


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
    except (ValueError, IndexError, TypeError):
        raise ValueError(f"frames: expected A:B (a slice over {len(frames)} frames), "
                         f"got {spec!r}") from None
    if not chosen:
        raise ValueError(f"frames: {spec!r} selects no frame of the {len(frames)} in the capture")
    return chosen
