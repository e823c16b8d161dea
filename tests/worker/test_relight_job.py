"""A relight job through the runner (no Celery): it takes a succeeded reconstruction's published
PLY and config, its capture and an envmap asset from the store, reports progress per view, and
publishes relit views, the orbit's MP4 and a relight.json that names ids, not worker paths;
inputs that cannot work fail the job as invalid_input with the reason. The same job on a real
worker behind the API: test_relight_celery.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from sqlalchemy import select, update
from worker_harness import add_capture, tiny_config

from worker.blobs import LocalBlobStore
from worker.models import Artifact, Asset, Job
from worker.runner import Runner
from worker.settings import WorkerSettings
from worker.store import JobStore, Owner, new_id


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory, tiny_capture: Path) -> Path:
    """A finished 40-step reconstruction of the tiny capture (a run directory)."""
    import torch

    from core.pipeline import reconstruct

    run = tmp_path_factory.mktemp("relight-job") / "run"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # several times faster for a model this small
    try:
        reconstruct(tiny_capture, run, preset="test", overrides=tiny_config(40), progress=False)
    finally:
        torch.set_num_threads(threads)
    return run


@pytest.fixture(scope="module")
def capture3(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny capture's cameras over three frames."""
    from core.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("relight-3") / "capture"
    synthesize(out, SynthConfig(frames=3, views=8, width=32, height=32, seed=2, ao_directions=8))
    return out


def add_source(store: JobStore, blobs, capture: Path, run: Path, frames: list[str]) -> str:
    """A succeeded reconstruct job of `capture` whose artifacts are `run`'s config and its
    first frame's PLY standing in for each of `frames`."""
    cap = add_capture(store, blobs, capture, capture_id=new_id("cap"))
    source = store.create("t1", "reconstruct", {"preset": "test"}, capture_id=cap)
    blobs.put_file(f"jobs/{source.id}/artifacts/config.json", run / "config.json")
    for frame in frames:
        blobs.put_file(f"jobs/{source.id}/artifacts/frames/{frame}/gaussians.ply",
                       run / "frames" / "000000" / "gaussians.ply")
    owner = Owner.current()
    store.claim(source.id, owner, 5, 3)
    store.finish(source.id, owner, "succeeded")
    return source.id


@pytest.fixture
def setup(tmp_path: Path, store_url: str, tiny_capture: Path, tiny_run: Path):
    """(settings, store, blobs, source job id, envmap asset id): a succeeded reconstruct job
    whose run directory is published as its artifacts, and an envmap asset."""
    settings = WorkerSettings(data_dir=tmp_path / "data", database_url=store_url,
                              heartbeat_seconds=0.2, lease_seconds=30)
    store = JobStore(store_url)
    blobs = LocalBlobStore(settings.data_dir / "store")
    source = add_source(store, blobs, tiny_capture, tiny_run, ["000000"])
    asset = new_id("ast")
    env = tiny_capture / "gt" / "envmaps" / "relight.exr"
    blobs.put_file(f"assets/{asset}/relight.exr", env)
    with store.session() as s:
        s.add(Asset(id=asset, tenant="t1", kind="envmap", filename="relight.exr",
                    size=env.stat().st_size, sha256="0" * 64, content_type="image/x-exr"))
    return settings, store, blobs, source, asset


def relight(store: JobStore, source: str, params: dict) -> str:
    job = store.create_render("t1", source, "relight", params)
    assert job is not None
    return job.id


def test_a_relight_job_publishes_relit_views_an_mp4_and_its_record(setup):
    settings, store, blobs, source, asset = setup
    lights = [{"kind": "directional", "direction": [0, -1, 0], "intensity": 2.0},
              {"kind": "point", "position": [0, -1, 1], "intensity": 1.0, "color": [1, .5, .2]}]
    job_id = relight(store, source, {"envmap": asset, "orbit": 4, "rotation_deg": 45,
                                     "lights": lights, "capture_light": 3.0})
    assert Runner(settings, store, blobs).run(job_id).status == "succeeded", \
        [r.line for r in store.logs(job_id, 0, 100)]
    with store.session(write=False) as s:
        listed = {a.path: (a.kind, a.frame) for a in s.scalars(
            select(Artifact).where(Artifact.job_id == job_id))}
    views = {f"relit/000000/orbit{i:03d}.{ext}" for i in range(4) for ext in ("png", "exr")}
    assert set(listed) == views | {"relit/000000.mp4", "relit/relight.json"}
    assert {listed[v] for v in views} == {("relit", "000000")}
    assert listed["relit/000000.mp4"] == ("video", "000000")
    assert listed["relit/relight.json"] == ("relight", None)
    record = json.loads(blobs.local_path(f"jobs/{job_id}/artifacts/relit/relight.json")
                        .read_text())
    assert record["run"] == f"jobs/{source}" and record["params"]["envmap"] == asset
    assert record["params"]["rotation_deg"] == 45 and record["views"] == 4
    assert [lt["kind"] for lt in record["params"]["lights"]] == ["directional", "point"]
    assert record["capture_light"] == "uniform 3"
    job = store.get(job_id)
    assert job.fraction == 1.0 and job.iterations == 4 and job.frames == 1
    progress = [e.data for e in store.events_after(job_id, 0) if e.kind == "progress"]
    # A 4-view render can finish within one heartbeat, so the stage "relighting" may never be
    # written on its own; the log line of the video is.
    logs = [r.line for r in store.logs(job_id, 0, 100)]
    assert any("frame 000000: video written (4/4 views)" in line for line in logs), logs
    fractions = [p["fraction"] for p in progress]
    assert fractions == sorted(fractions)
    assert not (settings.scratch / "jobs" / job_id).exists()  # scratch cleaned up


def test_a_slice_of_a_sequence_renders_only_its_frames_and_a_video_per_camera(
        setup, capture3: Path, tiny_run: Path):
    settings, store, blobs, _, asset = setup
    source = add_source(store, blobs, capture3, tiny_run, ["000000", "000001", "000002"])
    job_id = relight(store, source, {"envmap": asset, "frames": "1:"})
    assert Runner(settings, store, blobs).run(job_id).status == "succeeded", \
        [r.line for r in store.logs(job_id, 0, 100)]
    with store.session(write=False) as s:
        listed = {a.path: (a.kind, a.frame) for a in s.scalars(
            select(Artifact).where(Artifact.job_id == job_id))}
    assert set(listed) == {f"relit/{f}/cam00.{ext}" for f in ("000001", "000002")
                           for ext in ("png", "exr")} | {"relit/videos/cam00.mp4",
                                                         "relit/relight.json"}
    assert listed["relit/videos/cam00.mp4"] == ("video", None)
    record = json.loads(blobs.local_path(f"jobs/{job_id}/artifacts/relit/relight.json")
                        .read_text())
    assert record["frames"] == ["000001", "000002"] and record["params"]["frames"] == "1:"
    job = store.get(job_id)
    assert (job.frames, job.iterations) == (2, 2)


@pytest.mark.parametrize("envmap", ["builtin:neon", None])
def test_a_built_in_map_or_lights_alone(setup, envmap):
    settings, store, blobs, source, _ = setup
    light = {"kind": "directional", "direction": [0, -1, 0], "intensity": 2.0}
    job_id = relight(store, source, {"envmap": envmap, "lights": [light], "cameras": "cam00"})
    assert Runner(settings, store, blobs).run(job_id).status == "succeeded", \
        [r.line for r in store.logs(job_id, 0, 100)]
    record = json.loads(blobs.local_path(f"jobs/{job_id}/artifacts/relit/relight.json")
                        .read_text())
    assert record["params"]["envmap"] == envmap and record["views"] == 1
    assert any(map(any, record["envmap_sh9"])) == (envmap is not None)


@pytest.mark.parametrize("change, words", [
    ({"cameras": "cam99"}, "cam99"),
    ({"frames": "3"}, "frames"),
    ("delete envmap", "envmap: asset"),
    ("delete source", "was deleted"),
])
def test_relight_inputs_that_cannot_work_fail_clearly(setup, change, words):
    settings, store, blobs, source, asset = setup
    params = {"envmap": asset, **(change if isinstance(change, dict) else {})}
    job_id = relight(store, source, params)
    with store.session() as s:
        if change == "delete envmap":
            s.execute(Asset.__table__.delete().where(Asset.id == asset))
        elif change == "delete source":
            s.execute(update(Job).where(Job.id == job_id).values(source_job_id=None))
    assert Runner(settings, store, blobs).run(job_id).status == "failed"
    error = store.get(job_id).error
    assert error["code"] == "invalid_input" and not error["retryable"], error
    assert words in error["message"], error
    assert blobs.list(f"jobs/{job_id}/artifacts") == []


def test_the_api_knows_core_s_built_in_maps():
    from core.relight.presets import PRESETS
    from worker.pipelines import BUILTIN_ENVMAPS

    assert BUILTIN_ENVMAPS == tuple(PRESETS)


def test_an_export_job_publishes_a_stream_and_spz_of_the_reconstruction(
        setup, capture3: Path, tiny_run: Path):
    """`export` (POST /v1/exports) runs like a render: the source's frames in, export/ out."""
    from core.export.stream import read_stream

    settings, store, blobs, _, _ = setup
    source = add_source(store, blobs, capture3, tiny_run, ["000000", "000001", "000002"])
    job = store.create_render("t1", source, "export", {"formats": ["stream", "spz"], "fps": 12})
    assert Runner(settings, store, blobs).run(job.id).status == "succeeded", \
        [r.line for r in store.logs(job.id, 0, 100)]
    with store.session(write=False) as s:
        listed = {a.path: (a.kind, a.frame) for a in s.scalars(
            select(Artifact).where(Artifact.job_id == job.id))}
    spz = {f"export/spz/00000{i}.spz": ("spz", f"00000{i}") for i in range(3)}
    assert listed == {**spz, "export/stream.dgss": ("stream", None),
                      "export/export.json": ("export", None)}
    header, frames = read_stream(blobs.local_path(f"jobs/{job.id}/artifacts/export/stream.dgss"))
    assert header["fps"] == 12 and len(header["groups"]) == 3  # no sequence.json: one a frame
    assert len(header["cameras"]) == 8 and header["cameras"][0]["heldout"]
    assert len(list(frames)) == 3
    logs = [r.line for r in store.logs(job.id, 0, 100)]
    assert any("smaller than PLY" in line for line in logs), logs
    assert not (settings.scratch / "jobs" / job.id).exists()
