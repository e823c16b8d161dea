"""core.pipeline.reconstruct: the run directory of docs/design.md 3.3, config overrides, frame
selection, checkpoints and resume, progress only on a terminal."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from core.model import GaussianModel
from core.config import preset_config, read_run, train_config
from core.pipeline import Progress, Stopped, reconstruct
from core.synth import SynthConfig, synthesize
from core.training import Trainer

# Tiny tensors: a second intra-op thread only adds synchronisation.
pytestmark = pytest.mark.usefixtures("one_thread")

# A shortened `test` preset: every stage, densification, a reset and the AO bake in 100 steps
# (fewer leave the geometry branch too transparent to picture).
SHORT = {"train": {"schedule": {"iterations": 100, "stage2_start": 30, "stage3_start": 70,
                                "densify_from": 5, "densify_until": 60, "densify_interval": 10,
                                "reset_interval": 40, "sh_interval": 10},
                   "init_points": 500},
         "checkpoint_every": 10,
         "gop": 1}  # every frame a key frame: sequences are tested in test_sequence.py


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 views of 32x32, two frames, masks and normal priors, ground truth under gt/."""
    out = tmp_path_factory.mktemp("pipe") / "capture"
    synthesize(out, SynthConfig(frames=2, views=8, width=32, height=32, seed=2, priors=True,
                                ao_directions=8))
    return out


@pytest.fixture(scope="module")
def short_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "short.json"
    path.write_text(json.dumps(SHORT))
    return path


@pytest.fixture(scope="module")
def run(capture: Path, short_config: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("run") / "run"
    reconstruct(capture, out, preset="test", config_file=short_config, progress=False)
    torch.set_num_threads(before)
    return out


def test_run_directory_layout(run: Path, capture: Path):
    resolved = read_run(run)
    cfg = resolved.config
    assert resolved.preset == "test" and resolved.capture == str(capture.resolve())
    assert cfg.train.schedule.iterations == 100  # override applied
    assert cfg.train.densify.max_gaussians == 4_000  # the rest is the preset
    assert cfg.checkpoint_every == 10 and cfg.gop == 1
    assert resolved.frames == ("000000", "000001")
    for frame in resolved.frames:
        model = GaussianModel.load_ply(run / "frames" / frame / "gaussians.ply")
        assert len(model) > 0
        # Held-out camera of 8 is cam index 0 only; nothing rendered for training cameras.
        names = sorted(p.name for p in (run / "renders" / frame).iterdir())
        assert names == ["cam00_ao.png", "cam00_depth.npy", "cam00_normal.png", "cam00_rgb.png"]
        rgb = np.asarray(Image.open(run / "renders" / frame / "cam00_rgb.png"))
        assert rgb.shape == (32, 32, 3) and rgb.dtype == np.uint8 and rgb.max() > 50
        normal = np.asarray(Image.open(run / "renders" / frame / "cam00_normal.png"))
        n = normal.astype(np.float32) / 255 * 2 - 1
        fg = normal.sum(-1) > 0
        assert fg.mean() > 0.05 and not fg.all()  # the figure on a black background
        assert np.allclose(np.linalg.norm(n[fg], axis=-1), 1.0, atol=0.03)  # unit normals
        ao = np.asarray(Image.open(run / "renders" / frame / "cam00_ao.png"))
        assert ao.ndim == 2 and ao.shape == (32, 32)
        depth = np.load(run / "renders" / frame / "cam00_depth.npy")
        assert depth.dtype == np.float32 and depth.shape == (32, 32)
        # Cameras sit 3.2 m from the figure: covered pixels have plausible depths.
        assert 1.5 < float(np.median(depth[fg])) < 5.0
    assert not list((run / "checkpoints").glob("*.pt"))  # removed once a frame is finished
    for name in ("loss.png", "psnr.png", "gaussians.png"):
        assert Image.open(run / "plots" / name).size[0] > 100


def test_metrics(run: Path):
    m = json.loads((run / "metrics.json").read_text())
    assert "GoP" in m["note"] and m["gop"] == 1
    for frame in ("000000", "000001"):
        f = m["frames"][frame]
        assert f["iterations"] == 100 and f["seconds"] > 0 and f["gaussians"] > 0
        assert {"photometric", "total", "visibility"} <= set(f["final_losses"])
        assert 8 < f["train_psnr"] < 60 and f["normal_prior"] == "capture"
        steps = [r["step"] for r in f["history"]]
        assert steps == list(range(100))
        # Training made progress: the running PSNR at the end beats the start.
        ps = [r["psnr"] for r in f["history"]]
        assert np.mean(ps[-10:]) > np.mean(ps[:10]) + 1.0


def test_frames_subset_and_run_dir_checks(capture: Path, short_config: Path, tmp_path: Path):
    out = tmp_path / "run"
    reconstruct(capture, out, preset="test", frames="1:2", config_file=short_config,
                progress=False)
    assert [p.name for p in (out / "frames").iterdir()] == ["000001"]
    with pytest.raises(ValueError, match="--resume"):
        reconstruct(capture, out, preset="test", config_file=short_config, progress=False)
    with pytest.raises(ValueError, match="another configuration"):
        reconstruct(capture, out, preset="test", resume=True, progress=False)
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "x.txt").write_text("x")
    with pytest.raises(ValueError, match="not a run directory"):
        reconstruct(capture, tmp_path / "junk", preset="test", resume=True, progress=False)


def test_resume_after_interruption(capture: Path, short_config: Path, tmp_path: Path,
                                   monkeypatch: pytest.MonkeyPatch):
    out = tmp_path / "run"
    real_step = Trainer.train_step
    calls = {"n": 0}

    def crashing_step(self):
        calls["n"] += 1
        if calls["n"] == 100 + 85:  # frame 000001, step 84: after the AO bake (70) and the
            # checkpoint at 80
            raise RuntimeError("worker lost")
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", crashing_step)
    with pytest.raises(RuntimeError, match="worker lost"):
        reconstruct(capture, out, preset="test", config_file=short_config, progress=False)
    assert (out / "checkpoints" / "000001.pt").is_file()
    done = out / "frames" / "000000" / "gaussians.ply"
    stamp = done.stat().st_mtime_ns
    monkeypatch.setattr(Trainer, "train_step", real_step)
    m = reconstruct(capture, out, preset="test", config_file=short_config, resume=True,
                    progress=False)
    assert done.stat().st_mtime_ns == stamp  # the finished frame was skipped
    f = m["frames"]["000001"]
    assert f["resumed_at"] == 80
    # The history before the interruption came back with the checkpoint, then continued.
    assert [r["step"] for r in f["history"]] == list(range(100))
    assert "visibility" in f["final_losses"]  # baked AO targets came back as well
    assert (out / "frames" / "000001" / "gaussians.ply").is_file()


def test_progress_events_and_cooperative_stop(capture: Path, short_config: Path, tmp_path: Path):
    """A service watches every step, learns of each checkpoint once it is on disk, and stops a
    run between two steps; the run resumes from the step it stopped at."""
    out = tmp_path / "run"
    events: list[Progress] = []

    def watch(event: Progress) -> None:
        if event.kind == "checkpoint":
            assert Path(event.path).is_file()  # complete on disk when announced
        events.append(event)

    def stop() -> bool:
        return sum(e.kind == "step" for e in events) >= 45

    with pytest.raises(Stopped) as info:
        reconstruct(capture, out, preset="test", config_file=short_config, progress=False,
                    on_progress=watch, should_stop=stop)
    assert (info.value.frame, info.value.step) == ("000000", 45)
    steps = [e.step for e in events if e.kind == "step"]
    assert steps == list(range(1, 46)) and events[0].kind == "frame_start"
    assert {e.iterations for e in events} == {100} and {e.frames for e in events} == {2}
    assert [e.stage for e in events if e.kind == "step"][-1] == 2  # stage 2 starts at 30
    saved = [e.step for e in events if e.kind == "checkpoint"]
    assert saved == [10, 20, 30, 40, 45]  # every 10 steps, then the one written by the stop
    blob = torch.load(out / "checkpoints" / "000000.pt", weights_only=True)
    assert blob["step"] == 45

    events.clear()
    reconstruct(capture, out, preset="test", config_file=short_config, progress=False,
                resume=True, on_progress=watch)
    first = events[0]
    assert (first.kind, first.frame, first.step) == ("frame_start", "000000", 45)
    done = [e for e in events if e.kind == "frame_done"]
    assert [(e.frame, e.frame_index) for e in done] == [("000000", 0), ("000001", 1)]
    assert all(Path(e.path, "gaussians.ply").is_file() for e in done)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"]["000000"]["resumed_at"] == 45


def test_a_stop_between_frames_spends_nothing_on_the_next(capture: Path, short_config: Path,
                                                          tmp_path: Path):
    """A stop asked before a frame begins (a cancel right after a job's claim, a time budget at
    a frame boundary) stops there: none of that frame's setup, seeds or steps is spent and no
    checkpoint is written for it; a resumed run starts it afresh."""
    out = tmp_path / "run"
    with pytest.raises(Stopped) as info:
        reconstruct(capture, out, preset="test", config_file=short_config, progress=False,
                    should_stop=lambda: True)
    assert (info.value.frame, info.value.step) == ("000000", None)
    assert info.value.where == "the start of frame 000000"
    assert not list(out.rglob("*.pt")) and not list(out.rglob("gaussians.ply"))

    events: list[Progress] = []
    with pytest.raises(Stopped) as info:
        reconstruct(capture, out, preset="test", config_file=short_config, progress=False,
                    resume=True, on_progress=events.append,
                    should_stop=lambda: any(e.kind == "frame_done" for e in events))
    assert (info.value.frame, info.value.step) == ("000001", None)
    assert [e.frame for e in events if e.kind == "frame_start"] == ["000000"]
    assert not (out / "checkpoints" / "000001.pt").exists()

    events.clear()
    metrics = reconstruct(capture, out, preset="test", config_file=short_config,
                          progress=False, resume=True, on_progress=events.append)
    assert [e.frame for e in events if e.kind == "frame_start"] == ["000001"]
    assert events[0].step == 0 and list(metrics["frames"]) == ["000000", "000001"]
    assert metrics["frames"]["000001"]["resumed_at"] == 0  # begun afresh


def test_progress_bar_on_a_terminal_lines_elsewhere(capture: Path, short_config: Path,
                                                    tmp_path: Path, capsys: pytest.CaptureFixture,
                                                    monkeypatch: pytest.MonkeyPatch):
    reconstruct(capture, tmp_path / "a", preset="test", frames="0:1",
                config_file=short_config)
    # pytest's stderr is not a TTY: timed lines (the first, the last, and the summary), no bar.
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "frame 000000 (1/1): started, step 0/100"
    assert lines[-2].startswith("frame 000000 (1/1): step 100/100 stage 3 loss ")
    assert lines[-1].startswith("frame 000000 (1/1): trained 100 step(s) in ")
    assert not any("\r" in line or "gaussians=" in line for line in lines)
    monkeypatch.setattr("sys.stderr.isatty", lambda: True)
    reconstruct(capture, tmp_path / "b", preset="test", frames="0:1",
                config_file=short_config)
    err = capsys.readouterr().err
    assert "frame 000000 (1/1)" in err and "100/100" in err and "gaussians=" in err
    reconstruct(capture, tmp_path / "c", preset="test", frames="0:1",
                config_file=short_config, progress=False)
    assert capsys.readouterr().err == ""


def test_train_config_presets_unchanged():
    # The pipeline's resolved config is the preset when no file is given.
    assert preset_config("fast").train == train_config("fast")


def _cli(capsys: pytest.CaptureFixture, *argv: str) -> tuple[int, str, str]:
    from core.cli import main

    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_cli_reconstruct_and_eval(capture: Path, short_config: Path, tmp_path: Path,
                                  capsys: pytest.CaptureFixture):
    run = tmp_path / "run"
    rc, out, err = _cli(capsys, "reconstruct", capture, "--out", run, "--preset", "test",
                        "--frames", "1:", "--gop", "5", "--config", short_config)
    assert rc == 0, err
    assert "reconstructed 1 frame(s)" in out and "dgs eval" in out
    resolved = read_run(run)
    assert resolved.config.gop == 5 and resolved.frames == ("000001",)
    assert json.loads((run / "metrics.json").read_text())["gop"] == 5
    rc, out, err = _cli(capsys, "eval", run)
    assert rc == 0, err
    assert "PSNR" in out and "normal cosine" in out and (run / "eval.json").is_file()
    assert "LPIPS " in out


@pytest.mark.parametrize("case, expect", [
    ("missing", "not a valid capture: "),
    ("invalid", "capture.json"),
    ("preset", "--preset: expected one of paper, fast, test, got 'huge'"),
    ("frames", "frames: expected A:B"),
    ("empty_frames", "selects no frame"),
    ("exists", "already exists and is not empty; pass --resume"),
    ("not_a_run", "is not a run directory"),
    ("config_key", "c.json.bogus: unknown setting"),
    ("gop", "gop: Input should be greater than or equal to 1"),
    ("one_camera", "config.split: every8 leaves no camera to train on"),
    ("no_masks", "config.mesh.subject: the capture has no masks"),
])
def test_cli_reconstruct_bad_input(case: str, expect: str, capture: Path, tmp_path: Path,
                                   capsys: pytest.CaptureFixture):
    cap, out, extra = capture, tmp_path / "run", []
    if case == "missing":
        cap = tmp_path / "nowhere"
    elif case == "invalid":
        cap = tmp_path / "bad"
        cap.mkdir()
        (cap / "capture.json").write_text("{broken")
    elif case == "preset":
        extra = ["--preset", "huge"]
    elif case == "frames":
        extra = ["--frames", "a:b"]
    elif case == "empty_frames":
        extra = ["--frames", "5:9"]
    elif case in ("exists", "not_a_run"):
        out.mkdir()
        (out / "something.txt").write_text("x")
        extra = ["--resume"] if case == "not_a_run" else []
    elif case == "config_key":
        (tmp_path / "c.json").write_text('{"bogus": 1}')
        extra = ["--config", tmp_path / "c.json"]
    elif case == "gop":
        extra = ["--gop", "0"]
    elif case in ("one_camera", "no_masks"):  # issue 42: what the API refuses, the CLI too
        cap = tmp_path / "variant"
        shutil.copytree(capture, cap, ignore=shutil.ignore_patterns("gt"))
        if case == "one_camera":
            doc = json.loads((cap / "capture.json").read_text())
            doc["cameras"] = doc["cameras"][:1]
            (cap / "capture.json").write_text(json.dumps(doc))
            for extra_view in cap.glob("*/*/cam0[1-9].*"):
                extra_view.unlink()
        else:
            shutil.rmtree(cap / "masks")
            (tmp_path / "c.json").write_text('{"mesh": {"subject": true}}')
            extra = ["--config", tmp_path / "c.json"]
    rc, _, err = _cli(capsys, "reconstruct", cap, "--out", out, "--preset", "test", *extra) \
        if case != "preset" else _cli(capsys, "reconstruct", cap, "--out", out, *extra)
    assert rc != 0
    assert expect in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    if case not in ("exists", "not_a_run"):
        assert not out.exists()  # nothing written for bad input


def test_cli_eval_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture):
    rc, _, err = _cli(capsys, "eval", tmp_path)
    assert rc != 0 and "not a run directory" in err and len(err.strip().splitlines()) == 1


def test_contact_sheet(run: Path, capture: Path, tmp_path: Path):
    from core.relight.sheet import LABEL_HEIGHT, contact_sheet

    relit = {("000000", "cam00"): {"builtin:studio": np.full((32, 32, 3), 0.5)}}
    out = contact_sheet(capture, run, [("000000", "cam00")], relit, tmp_path / "sheet.png",
                        scale=2)
    sheet = np.asarray(Image.open(out).convert("RGB"))
    columns = ["capture", "render", "normal", "AO", "studio", "ground-truth normal"]
    assert sheet.shape == (LABEL_HEIGHT + 64, len(columns) * 64, 3)
    body = sheet[LABEL_HEIGHT:]
    tiles = [body[:, i * 64:(i + 1) * 64] for i in range(len(columns))]
    assert all(t.max() > 0 for t in tiles)  # every column shows something
    # The render column is the run's rgb picture, upscaled 2x nearest; the relit one as given.
    rgb = np.asarray(Image.open(run / "renders" / "000000" / "cam00_rgb.png"))
    assert np.array_equal(tiles[1][::2, ::2], rgb)
    assert (tiles[4] == 128).all()
    with pytest.raises(ValueError, match="views"):
        contact_sheet(capture, run, [], {}, tmp_path / "none.png")

    # A real capture: JPEG images at 1080x1920 and a run at a quarter of that (the fox).
    jpg = tmp_path / "jpg"
    (jpg / "images" / "000000").mkdir(parents=True)
    Image.new("RGB", (1080, 1920), (200, 120, 40)).save(jpg / "images" / "000000" / "cam00.jpg")
    big = tmp_path / "big-run"
    (big / "renders" / "000000").mkdir(parents=True)
    Image.new("RGB", (270, 480), (10, 200, 10)).save(big / "renders" / "000000" / "cam00_rgb.png")
    out = contact_sheet(jpg, big, [("000000", "cam00")], {}, tmp_path / "big.png", scale=2)
    sheet = np.asarray(Image.open(out).convert("RGB"))
    assert sheet.shape == (LABEL_HEIGHT + 512, 4 * 288, 3)  # tiles of at most 512 px
    pixel = sheet[LABEL_HEIGHT + 256, 144].astype(int)  # the JPEG (lossy), not black
    assert (abs(pixel - (200, 120, 40)) <= 4).all(), pixel

    # Masks that mark a subject inside a scene (`masks: subject`, Panoptic's) leave the capture
    # tile whole; mattes cut the subject out of it.
    (jpg / "masks" / "000000").mkdir(parents=True)
    Image.new("L", (1080, 1920), 0).save(jpg / "masks" / "000000" / "cam00.png")
    for matte, expected in ((False, (200, 120, 40)), (True, (0, 0, 0))):
        out = contact_sheet(jpg, big, [("000000", "cam00")], {}, tmp_path / f"{matte}.png",
                            matte=matte)
        pixel = np.asarray(Image.open(out).convert("RGB"))[LABEL_HEIGHT + 256, 144].astype(int)
        assert (abs(pixel - expected) <= 4).all(), (matte, pixel)


def test_relight_over_frames_writes_a_video_per_camera(run: Path, tmp_path: Path):
    from core.relight import relight_run
    from core.relight.output import read_mp4_info

    record = relight_run(run, tmp_path / "relit", envmap="builtin:studio", cameras="cam01,cam02",
                         fps=5)
    assert record["frames"] == ["000000", "000001"] and record["views"] == 4
    assert record["videos"] == ["videos/cam01.mp4", "videos/cam02.mp4"]
    info = read_mp4_info(tmp_path / "relit" / "videos" / "cam01.mp4")
    assert info["frames"] == 2 and (info["width"], info["height"]) == (32, 32)
