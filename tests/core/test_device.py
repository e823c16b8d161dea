"""Where training runs: `core.device`, TrainConfig.device, `--device` on `dgs reconstruct` and
`dgs eval`, checkpoints that resume on any device; and, on a machine with CUDA, a tiny
reconstruction trained on the GPU against the same one on the CPU."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from core.data import CaptureDataset, load_capture
from core.device import resolve_device, to_device
from core.config import apply_overrides, preset_config as resolve_config
from core.config import ResolvedRun, TrainConfig, read_run, train_config
from core.training import Trainer, View, training_cameras


def _cuda_usable() -> bool:
    from native._backend import cuda_build

    return torch.cuda.is_available() and cuda_build()


CUDA = _cuda_usable()

# The conftest's shortened `test` preset (every stage, densification, a reset, the AO bake).
SHORT = {"train": {"schedule": {"iterations": 100, "stage2_start": 30, "stage3_start": 70,
                                "densify_from": 5, "densify_until": 60, "densify_interval": 10,
                                "reset_interval": 40, "sh_interval": 10},
                   "init_points": 500}}


@pytest.fixture
def no_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    """This process sees no GPU, whatever the machine has."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


@pytest.fixture(scope="module")
def views(synth_capture: Path) -> list[View]:
    cap = load_capture(synth_capture)
    ids = [c.id for c in training_cameras(cap)]
    ds = CaptureDataset(cap, frames=[cap.frames[0]], cameras=ids)
    return [View.from_sample(ds[i]) for i in range(len(ds))]


def _short_config(device: str, iterations: int | None = None) -> TrainConfig:
    cfg = apply_overrides(resolve_config("test"), SHORT, where="test").train
    if iterations is not None:
        cfg = replace(cfg, schedule=cfg.schedule.scaled(iterations))
    return replace(cfg, device=device)


def _tensors(obj) -> list[torch.Tensor]:
    if isinstance(obj, torch.Tensor):
        return [obj]
    if isinstance(obj, dict):
        return [t for v in obj.values() for t in _tensors(v)]
    if isinstance(obj, (list, tuple)):
        return [t for v in obj for t in _tensors(v)]
    return []


# -- choosing the device ---------------------------------------------------------------------
def test_resolve_device(monkeypatch: pytest.MonkeyPatch):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cpu")  # tests/conftest.py: DGS_DEVICE=cpu
    monkeypatch.delenv("DGS_DEVICE")
    assert resolve_device("auto").type == ("cuda" if CUDA else "cpu")
    if CUDA:
        assert resolve_device("cuda") == resolve_device("auto") == torch.device("cuda:0")
    for bad in ("gpu", "cuda:x", "CPU", "", None, 0):
        with pytest.raises(ValueError, match="expected auto, cpu, cuda or cuda:N"):
            resolve_device(bad)
    monkeypatch.setenv("DGS_DEVICE", "gpu")
    with pytest.raises(ValueError, match="DGS_DEVICE: expected auto, cpu, cuda or cuda:N"):
        resolve_device("auto")
    assert resolve_device("cpu") == torch.device("cpu")  # an explicit name ignores it


def test_cuda_without_cuda_is_a_clear_error(no_cuda, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.delenv("DGS_DEVICE")
    assert resolve_device("auto") == torch.device("cpu")
    for spec in ("cuda", "cuda:0"):
        with pytest.raises(ValueError, match=r"device: 'cuda(:0)?' asked for, but .*use "
                                             r"--device cpu"):
            resolve_device(spec)


def test_train_config_device_field():
    assert TrainConfig().device == "auto" and train_config("test").device == "auto"
    assert json.loads(json.dumps(train_config("test").to_dict()))["device"] == "auto"
    assert replace(TrainConfig(), device="cuda:1").device == "cuda:1"  # checked when used
    with pytest.raises(ValueError, match="device: expected auto, cpu, cuda or cuda:N, got 'gpu'"):
        replace(TrainConfig(), device="gpu")
    # A --config file or the service's overrides may set it; a bad one names the key.
    with pytest.raises(ValueError, match="device"):
        apply_overrides(resolve_config("test"), {"train": {"device": "tpu"}})


def test_trainer_runs_on_cpu_and_auto(views: list[View], one_thread):
    for spec in ("cpu", "auto"):  # auto: the CPU in the tests
        trainer = Trainer(views, _short_config(spec, iterations=3))
        trainer.train()
        assert trainer.device == torch.device("cpu")
        assert all(p.device.type == "cpu" for p in trainer.model.params.values())
        assert math.isfinite(trainer.evaluate())


def test_trainer_asked_for_cuda_without_it_fails_before_training(views: list[View], no_cuda):
    with pytest.raises(ValueError, match="config.device: 'cuda' asked for"):
        Trainer(views, _short_config("cuda"))


def test_cli_device_without_cuda(synth_capture: Path, tmp_path: Path, no_cuda,
                                 capsys: pytest.CaptureFixture):
    from core.cli import main

    out = tmp_path / "run"
    rc = main(["reconstruct", str(synth_capture), "--out", str(out), "--preset", "test",
               "--device", "cuda"])
    err = capsys.readouterr().err
    assert rc == 2 and "dgs reconstruct: device: 'cuda' asked for" in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()  # nothing written
    rc = main(["reconstruct", str(synth_capture), "--out", str(out), "--device", "gpu"])
    assert rc == 2 and "device: expected auto, cpu, cuda or cuda:N" in capsys.readouterr().err


def test_cli_eval_device_without_cuda(tiny_run: Path, no_cuda, capsys: pytest.CaptureFixture):
    from core.cli import main

    rc = main(["eval", str(tiny_run), "--device", "cuda:0"])
    err = capsys.readouterr().err
    assert rc == 2 and "dgs eval: device: 'cuda:0' asked for" in err, err


def test_config_json_records_the_resolved_device(tiny_run: Path):
    assert read_run(tiny_run).config.train.device == "cpu"  # auto, pinned to the CPU here


def test_resume_ignores_the_device_and_accepts_records_without_one(tiny_run: Path):
    record = read_run(tiny_run)
    other = record.on_device("cuda:3")
    # A version 1 record written before train.device existed (the configuration at the top).
    flat = {**record.to_json()["config"], "version": 1, "preset": record.preset,
            "capture": record.capture, "frames": list(record.frames)}
    del flat["train"]["device"]
    old = ResolvedRun.from_json(flat)
    assert old.config.train.device == "auto"
    # (a record of before `densify_epoch` reads with it off: the interval its run densified at;
    # and of before `normal_confidence` with `per_view`: how its priors' confidences weighed)
    then = replace(record.config.train.schedule, densify_epoch=False)
    losses = replace(record.config.train.losses, normal_confidence="per_view")
    legacy = replace(record, config=replace(record.config, train=replace(
        record.config.train, schedule=then, losses=losses)))
    assert old.same_run(legacy) and not old.same_run(record)
    assert other.same_run(record) and record.same_run(other)
    eps = replace(other.config.train, eps2d=0.3)
    assert not replace(other, config=replace(other.config, train=eps)).same_run(record)


# -- checkpoints -----------------------------------------------------------------------------
def test_checkpoint_holds_cpu_tensors_and_round_trips(views: list[View], tmp_path: Path,
                                                      one_thread):
    cfg = _short_config("cuda" if CUDA else "cpu", iterations=12)
    trainer = Trainer(views, cfg)
    for _ in range(7):
        trainer.train_step()
    trainer.save_checkpoint(tmp_path / "ckpt.pt")
    # No map_location: every tensor comes back where it was saved, which must be the CPU.
    blob = torch.load(tmp_path / "ckpt.pt", weights_only=True)
    assert _tensors(blob) and all(t.device.type == "cpu" for t in _tensors(blob))
    resumed = Trainer(views, replace(cfg, device="cpu"))
    resumed.load_checkpoint(tmp_path / "ckpt.pt")
    assert resumed.step == 7 and resumed.state.history == trainer.state.history
    moments = 0
    for name, p in trainer.model.params.items():
        assert torch.equal(resumed.model.params[name].cpu(), p.detach().cpu()), name
        state = resumed.optimizer.state[resumed.model.params[name]]
        if state:  # a parameter no loss has reached yet (visibility before stage 3) has none
            assert state["exp_avg"].device == resumed.model.params[name].device
            moments += 1
    assert moments >= 5
    assert resumed.state.grad_c.device.type == "cpu"


def test_to_device_keeps_structure():
    blob = {"a": [torch.ones(2), (torch.zeros(1), 3)], "b": "x", "c": None}
    moved = to_device(blob, "cpu")
    assert moved["a"][0] is blob["a"][0]  # already there: not copied
    assert isinstance(moved["a"][1], tuple) and moved["a"][1][1] == 3 and moved["b"] == "x"


# -- on a GPU ----------------------------------------------------------------------------------
@pytest.mark.gpu
@pytest.mark.skipif(not CUDA, reason="needs a CUDA GPU and the native extension's CUDA build")
def test_cuda_reconstruction_matches_cpu_and_resumes_on_cpu(views: list[View], synth_capture,
                                                           tmp_path: Path):
    from core.training import Callback, CheckpointCallback

    class Losses(Callback):
        def __init__(self):
            self.totals: list[float] = []

        def on_step_end(self, trainer, info):
            self.totals.append(info.losses["total"])

    results = {}
    for spec in ("cpu", "cuda"):
        losses = Losses()
        trainer = Trainer(views, _short_config(spec), callbacks=[
            losses, CheckpointCallback(tmp_path / spec, every=50)])
        trainer.train()
        assert all(math.isfinite(v) for v in losses.totals), spec
        results[spec] = (trainer, trainer.evaluate())
    gpu, gpu_psnr = results["cuda"]
    cpu_psnr = results["cpu"][1]
    assert abs(gpu_psnr - cpu_psnr) < 1.0, (cpu_psnr, gpu_psnr)
    assert gpu.device.type == "cuda"
    assert all(p.device.type == "cuda" for p in gpu.model.params.values())
    assert all(t.device.type == "cuda" for t in _tensors(gpu.optimizer.state_dict()["state"])
               if t.dim() > 0)
    assert all(t.device.type == "cuda" for t in gpu.ao_targets)
    assert gpu.state.grad_c.device.type == "cuda" and gpu.views[0].image.device.type == "cuda"
    # The GPU's last checkpoint resumes on the CPU (and renders there).
    on_cpu = Trainer(views, _short_config("cpu"))
    on_cpu.load_checkpoint(tmp_path / "cuda" / "checkpoint.pt")
    assert on_cpu.step == gpu.step and len(on_cpu.model) == len(gpu.model)
    for name, p in gpu.model.params.items():
        assert torch.equal(on_cpu.model.params[name], p.detach().cpu()), name
    assert abs(on_cpu.evaluate() - gpu_psnr) < 0.1
    print(f"tiny reconstruction: CPU {cpu_psnr:.2f} dB, CUDA {gpu_psnr:.2f} dB")


@pytest.mark.gpu
@pytest.mark.skipif(not CUDA, reason="needs a CUDA GPU and the native extension's CUDA build")
def test_cuda_pipeline_end_to_end(synth_capture: Path, tmp_path: Path):
    """`reconstruct(device='cuda')` (checkpoints, held-out renders, PLY, meshes) and `dgs eval`
    rendering on the GPU; then the run resumes on the CPU from a checkpoint the GPU wrote."""
    from core.evaluation import evaluate_run
    from core.pipeline import Stopped, reconstruct

    overrides = {**SHORT, "gop": 1, "checkpoint_every": 20}
    run = tmp_path / "run"
    metrics = reconstruct(synth_capture, run, preset="test", frames="0:1", overrides=overrides,
                          progress=False, device="cuda")
    frame = metrics["frames"]["000000"]
    assert read_run(run).config.train.device.startswith("cuda")
    assert math.isfinite(frame["train_psnr"]) and frame["train_psnr"] > 10
    result = evaluate_run(run, device="cuda")
    assert math.isfinite(result["psnr"])
    stopped = tmp_path / "stopped"
    steps: list[int] = []  # stopped after the first step (a stop before it trains nothing)
    with pytest.raises(Stopped):
        reconstruct(synth_capture, stopped, preset="test", frames="0:1", overrides=overrides,
                    progress=False, device="cuda", should_stop=lambda: bool(steps),
                    on_progress=lambda e: e.kind == "step" and steps.append(e.step))
    resumed = reconstruct(synth_capture, stopped, preset="test", frames="0:1",
                          overrides=overrides, progress=False, device="cpu", resume=True)
    assert resumed["frames"]["000000"]["resumed_at"] == 1
    assert abs(resumed["frames"]["000000"]["train_psnr"] - frame["train_psnr"]) < 1.0
