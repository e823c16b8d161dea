"""`relight_run`: relit renders of a finished run (what `dgs relight` and the service's render
jobs call), with progress events and a cooperative stop, in the manner of core.pipeline.

Output (docs/design.md 3.2): OUT/<frame>/<camera>.png (sRGB) and .exr (linear, premultiplied RGBA);
with an orbit or a camera path also OUT/<frame>.mp4 (the views around one frame); with capture
cameras over several frames OUT/videos/<camera>.mp4 (the performance seen by that camera);
OUT/relight.json records the parameters, the map's SH9 coefficients and the files.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch
from pydantic import Field, ValidationError, model_validator

from core.color import linear_to_srgb
from core.config.relight import RelightSettings
from core.config import parse_frames
from core.data import load_capture
from core.data.images import read_image
from core.files import write_json
from core.model import GaussianModel
from core.relight.cameras import load_camera_path, orbit_cameras, select_cameras
from core.relight.envmap import load_envmap
from core.relight.gbuffer import gbuffer, run_render
from core.relight.lights import CaptureLight, load_capture_light
from core.relight.output import Mp4Writer, to_uint8, write_views
from core.relight.shade import shade

if TYPE_CHECKING:
    from core.data.capture import Capture
    from core.relight.envmap import EnvMap
    from core.relight.gbuffer import RunRender

__all__ = ["Plan", "RelightParams", "RelightProgress", "RelightStopped", "compose",
           "frame_cameras", "prepare", "relight_run", "relight_view", "run_params",
           "view_gbuffer"]


class RelightParams(RelightSettings):
    """What `dgs relight` renders: the shared settings (`core.config.relight.RelightSettings`)
    with what only a local user may name, files on this machine."""

    camera_path: str | None = Field(
        None, min_length=1, max_length=4096,
        description="A nerfstudio camera_path.json to render (and an MP4 per frame).")
    capture_light: float | str | None = Field(
        None, description="The capture's own lighting the albedo is divided by: None for a "
                          "uniform irradiance of pi, a number (uniform irradiance), a stage "
                          ".exr/.hdr map, or a .json with sh9_radiance (9x3).")

    @model_validator(mode="after")
    def _one_path(self) -> RelightParams:
        if self.orbit is not None and self.camera_path is not None:
            raise ValueError("orbit, camera_path: give one of them, not both")
        return self

    def to_json(self) -> dict:
        return self.model_dump(mode="json")


@dataclass(frozen=True)
class RelightProgress:
    """One event of `relight_run(on_progress=...)`; `done / total` never decreases."""

    kind: Literal["start", "view", "video", "done"]
    """'start' (inputs checked), 'view' (a view's files written), 'video' (an MP4
    written), 'done' (everything written)."""
    done: int
    """Views written so far, over all frames."""
    total: int
    """Views to write in all."""
    frame: str | None = None
    """The frame the event is about."""
    path: str | None = None
    """The file written (the view's PNG, or the MP4)."""


class RelightStopped(Exception):
    """`should_stop()` returned True between two views; the files already written stay."""

    def __init__(self, done: int, total: int):
        super().__init__(f"relight stopped after {done} of {total} views")
        self.done, self.total = done, total


@dataclass
class Plan:
    """Everything a relight needs, checked (`prepare`)."""

    settings: RunRender
    """How the run renders its models."""
    capture: Capture
    """The run's capture."""
    frames: list[str]
    """Frames to relight."""
    env: EnvMap | None
    """The environment map (None: black, lights only)."""
    capture_light: CaptureLight
    """The lighting the albedo is divided by."""
    linear: bool
    """The capture stores linear colour (EXR); else sRGB."""
    path_cams: list | None = None
    """Cameras of a camera path, when one was given."""
    fps: float = 24.0
    """MP4 frame rate."""
    files: list[str] = field(default_factory=list)
    """Files written so far (relative to the output folder)."""

    @property
    def env_sh9(self) -> np.ndarray:
        """(9, 3) radiance SH of the environment (zero for a black one)."""
        return np.zeros((9, 3)) if self.env is None else self.env.sh9


def prepare(run: Path, params: RelightParams, capture_dir) -> Plan:
    """Check every input before anything is written."""
    settings = run_render(run, capture_dir)
    capture = load_capture(settings.capture)
    env = None if params.envmap is None else load_envmap(params.envmap, capture.up,
                                                         params.rotation_deg, params.exposure)
    cap_light = load_capture_light(params.capture_light, capture.up)
    finished = [f for f in capture.frames if (run / "frames" / f / "gaussians.ply").is_file()]
    if not finished:
        raise ValueError(f"run_dir: {run} has no finished frame (no frames/<frame>/gaussians.ply)")
    frames = parse_frames(params.frames, finished)
    if params.camera_path is None and params.orbit is None:
        select_cameras(capture, params.cameras, settings.views)
    first = capture.image_path(capture.frames[0], capture.cameras[0].id)
    plan = Plan(settings, capture, frames, env, cap_light,
                first is not None and first.suffix.lower() == ".exr", fps=params.fps)
    if params.camera_path is not None:
        plan.path_cams, fps = load_camera_path(params.camera_path)
        plan.fps = fps or params.fps
    return plan


def _subject_center(model) -> np.ndarray:
    """Median of the means of the Gaussians opaque in the geometry branch (robust to floaters)."""
    with torch.no_grad():
        keep = model.opacity_g > 0.5
        means = model.means[keep] if int(keep.sum()) >= 10 else model.means
        return means.median(dim=0).values.double().cpu().numpy()


def frame_cameras(plan: Plan, params: RelightParams, model) -> list:
    served = [plan.settings.views.served(c) for c in plan.capture.cameras]
    if plan.path_cams is not None:
        return plan.path_cams
    if params.orbit is not None:
        return orbit_cameras(served, _subject_center(model), plan.capture.up, params.orbit)
    ids = {c.id for c in select_cameras(plan.capture, params.cameras, plan.settings.views)}
    return [c for c in served if c.id in ids]


def view_gbuffer(model, camera, plan: Plan):
    """The G-buffer of `model` seen by `camera` (core.data.Camera) with the run's settings, on
    the model's device."""
    return gbuffer(model, plan.settings.camera(camera, device=model.means.device),
                   plan.settings, linear_capture=plan.linear)


def compose(g, plan: Plan, env_sh9, lights=(), *, ao: bool = True,
            match_exposure: bool = False):
    """Shade G-buffer `g` under `env_sh9` (9, 3) plus `lights`: (sRGB composited on the run's
    background (H, W, 3) numpy, linear premultiplied RGBA (H, W, 4) numpy). `match_exposure`
    scales the result so that its mean luminance over the covered pixels is that of the
    reconstruction under the capture's own light (a camera's auto exposure: pictures under maps
    much brighter or darker than the stage stay readable)."""
    s = shade(g, env_sh9, plan.capture_light, lights, ao=ao)
    linear = s.linear
    if match_exposure:
        w = (s.alpha > 0.5).float()
        # Rec. 709 luminance weights
        lum = torch.tensor([0.2126, 0.7152, 0.0722], device=linear.device)
        have = float((w * ((g.base + g.residual).clamp_min(0) @ lum)[..., None]).sum())
        got = float((w * (linear @ lum)[..., None]).sum())
        linear = linear * (have / got if got > 1e-8 and have > 0 else 1.0)
    bg = torch.tensor(plan.settings.background, dtype=torch.float32, device=linear.device)
    bg_srgb = linear_to_srgb(bg) if plan.linear else bg
    srgb = linear_to_srgb(linear) * s.alpha + bg_srgb * (1 - s.alpha)
    rgba = torch.cat([linear * s.alpha, s.alpha], dim=-1)
    return srgb.cpu().numpy(), rgba.cpu().numpy()


def relight_view(model, camera, plan: Plan, params: RelightParams, *, ao: bool | None = None):
    """(sRGB composited (H, W, 3) numpy, linear premultiplied RGBA (H, W, 4) numpy)."""
    return compose(view_gbuffer(model, camera, plan), plan, plan.env_sh9, params.lights,
                   ao=params.ao if ao is None else ao)


def relight_run(run_dir, out_dir, *, envmap=None, rotation_deg: float = 0.0, exposure: float = 0.0,
                lights=(), cameras: str = "heldout", frames: str | None = None,
                orbit: int | None = None, camera_path=None, capture_dir=None,
                on_progress: Callable[[RelightProgress], None] | None = None,
                should_stop: Callable[[], bool] | None = None, capture_light=None,
                ao: bool = True, fps: float = 24.0) -> dict:
    """Relight the run's frames (see `RelightParams` for the parameters; `lights` may hold
    `Light`s or their JSON dicts); returns the record also written to OUT/relight.json.

    Every input is checked before anything is written (ValueError naming the argument).
    `on_progress` receives `RelightProgress` events; `should_stop` is asked before each view and
    when it returns True `RelightStopped` is raised (files already written stay)."""
    try:
        params = RelightParams(
            envmap=None if envmap is None else str(envmap), rotation_deg=rotation_deg,
            exposure=exposure, lights=tuple(lights), cameras=cameras, frames=frames,
            orbit=orbit, camera_path=None if camera_path is None else str(camera_path),
            capture_light=None if capture_light is None else str(capture_light), ao=ao, fps=fps)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(map(str, first["loc"])) or "params"
        raise ValueError(f"{where}: {first['msg'].removeprefix('Value error, ')}") from None
    return run_params(run_dir, out_dir, params, capture_dir=capture_dir,
                      on_progress=on_progress, should_stop=should_stop)


def run_params(run_dir, out_dir, params: RelightParams, *, capture_dir=None,
               on_progress=None, should_stop=None) -> dict:
    """`relight_run` with the parameters as one `RelightParams`."""
    start = time.perf_counter()
    run, out = Path(run_dir), Path(out_dir)
    plan = prepare(run, params, capture_dir)
    emit = on_progress or (lambda event: None)
    total = _views_per_frame(plan, params) * len(plan.frames)
    done, videos = 0, []
    emit(RelightProgress("start", 0, total))
    orbit = params.orbit is not None or params.camera_path is not None
    for frame in plan.frames:  # one model in memory at a time
        model = GaussianModel.load_ply(run / "frames" / frame / "gaussians.ply")
        writer = None
        try:
            for cam in frame_cameras(plan, params, model):
                if should_stop is not None and should_stop():
                    raise RelightStopped(done, total)
                srgb, rgba = relight_view(model, cam, plan, params)
                files = write_views(out / frame / cam.id, srgb, rgba)
                plan.files += [str(p.relative_to(out)) for p in files]
                if orbit:
                    writer = writer or Mp4Writer(out / f"{frame}.mp4", cam.width, cam.height,
                                                 plan.fps)
                    writer.write(to_uint8(srgb))
                done += 1
                emit(RelightProgress("view", done, total, frame, str(files[0])))
        finally:
            if writer is not None:
                writer.close()
        if writer is not None:
            videos.append(f"{frame}.mp4")
            emit(RelightProgress("video", done, total, frame, str(out / f"{frame}.mp4")))
    if not orbit and len(plan.frames) > 1:
        videos += _camera_videos(out, plan, params, emit, done, total)
    record = {"version": 1, "run": str(run.resolve()), "params": params.to_json(),
              "envmap_sh9": plan.env_sh9.tolist(), "capture_light": plan.capture_light.source,
              "frames": plan.frames, "views": done, "files": plan.files, "videos": videos,
              "seconds": round(time.perf_counter() - start, 3)}
    write_json(out / "relight.json", record)
    emit(RelightProgress("done", done, total, path=str(out / "relight.json")))
    return record


def _views_per_frame(plan: Plan, params: RelightParams) -> int:
    if plan.path_cams is not None:
        return len(plan.path_cams)
    if params.orbit is not None:
        return params.orbit
    return len(select_cameras(plan.capture, params.cameras, plan.settings.views))


def _camera_videos(out: Path, plan: Plan, params: RelightParams, emit, done: int,
                   total: int) -> list[str]:
    """OUT/videos/<camera>.mp4: each capture camera's view over the relit frames (the performance
    under the new light), encoded from the PNGs written."""
    names = []
    for cam in select_cameras(plan.capture, params.cameras, plan.settings.views):
        path = out / "videos" / f"{cam.id}.mp4"
        first = read_image(out / plan.frames[0] / f"{cam.id}.png")
        with Mp4Writer(path, first.shape[1], first.shape[0], plan.fps) as writer:
            for frame in plan.frames:
                writer.write(to_uint8(read_image(out / frame / f"{cam.id}.png")[..., :3]))
        names.append(f"videos/{cam.id}.mp4")
        emit(RelightProgress("video", done, total, None, str(path)))
    return names
