"""The sequence on CUDA against the CPU (skipped without a GPU): the deformation graph and the
deformed Gaussians, a tracked frame fitted on each device from the same key frame, and the
scene mode's frozen stage, which must not move by a bit on CUDA either.

The two devices run the same arithmetic in another order (CUDA's atomic gradient sums), so a
fitted frame agrees within tolerances, not bit for bit: positions to 1% of the scene's extent
at worst and 0.1% on average, rotations to 2.6 degrees for 99% of the Gaussians, renders to
30 dB of each other."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from core.config import read_run


def _cuda_ready() -> tuple[bool, str]:
    if not torch.cuda.is_available():
        return False, "no CUDA device (the sequence's CUDA path is tested on a GPU machine)"
    from native._backend import has_cuda

    if not has_cuda():
        return False, "the native extension was built without CUDA (nvcc missing or DGS_CUDA=0)"
    return True, ""


_READY, _WHY = _cuda_ready()
pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not _READY, reason=_WHY)]

RUN = {"train": {"schedule": {"iterations": 40, "stage2_start": 12, "stage3_start": 28,
                              "densify_from": 2, "densify_until": 24, "densify_interval": 5,
                              "reset_interval": 15, "sh_interval": 5},
                 "init_points": 300},
       # No growth and no transparency pruning in the refine stage: both devices keep the same
       # Gaussians, so they can be compared one by one.
       "sequence": {"num_nodes": 32, "deform_fraction": 0.5, "refine_fraction": 0.5,
                    "deform_views": 2, "max_growth": 0.0}}


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory):
    """The capture, the configuration and a key frame fitted on the CPU."""
    from core.config import load_config
    from core.synth import SynthConfig, synthesize
    from core.training import Trainer, frame_views

    out = tmp_path_factory.mktemp("seq-cuda") / "capture"
    synthesize(out, SynthConfig(frames=2, views=8, width=32, height=32, seed=4, priors=True,
                                ao_directions=8))
    from core.data import load_capture

    capture = load_capture(out)
    cfg = load_config("test", overrides=RUN)
    train = replace(cfg.train, device="cpu", densify=replace(cfg.train.densify, transparent=0.0))
    torch.manual_seed(0)
    key = Trainer(frame_views(capture, "000000"), train).train()
    return capture, train, cfg.sequence, key


def _tracker(setup, device: str, moving: torch.Tensor | None = None):
    from core.sequence import FrameTracker
    from core.training import frame_views

    capture, train, seq, key = setup
    model = type(key)({k: v.detach().clone() for k, v in key.params.items()})
    ids = torch.arange(len(key))
    return FrameTracker(frame_views(capture, "000001"), model, ids, len(key),
                        replace(train, device=device), seq, moving=moving)


def test_the_graph_and_the_deformation_on_cuda_match_the_cpu(setup):
    from core.sequence import DeformedGaussians, build_graph

    key = setup[3]
    points = key.means.detach()
    cpu, gpu = build_graph(points, 32), build_graph(points.cuda(), 32)
    assert gpu.nodes.device.type == "cuda"
    assert torch.equal(cpu.anchors, gpu.anchors.cpu()) and torch.equal(cpu.edges,
                                                                       gpu.edges.cpu())
    torch.testing.assert_close(gpu.weights.cpu(), cpu.weights, rtol=1e-5, atol=1e-6)
    g = torch.Generator().manual_seed(1)
    q = torch.nn.functional.normalize(torch.randn(32, 4, generator=g) * 0.1
                                      + torch.tensor([1.0, 0, 0, 0]), dim=-1)
    t = torch.randn(32, 3, generator=g) * 0.05
    a = DeformedGaussians(key, cpu, q, t)
    b = DeformedGaussians(key.to("cuda"), gpu, q.cuda(), t.cuda())
    for name in ("means", "quats", "normals"):
        torch.testing.assert_close(getattr(b, name).cpu(), getattr(a, name), rtol=1e-5,
                                   atol=1e-5)


def test_a_tracked_frame_on_cuda_matches_the_cpu(setup):
    from core.metrics import psnr
    from core.seeding import scene_extent

    torch.manual_seed(0)
    cpu = _tracker(setup, "cpu")
    cpu.train()
    gpu = _tracker(setup, "cuda")
    assert gpu.model.device.type == "cuda" and gpu.graph.nodes.device.type == "cuda"
    gpu.train()
    assert gpu.model.device.type == "cuda"
    assert gpu.start == cpu.start and gpu.refine_steps == cpu.refine_steps
    assert len(gpu.model) == len(cpu.model) and torch.equal(gpu.ids.cpu(), cpu.ids)
    extent = scene_extent([v.camera for v in cpu.views])
    moved = (gpu.model.means.detach().cpu() - cpu.model.means.detach()).norm(dim=1)
    assert float(moved.max()) < 1e-2 * extent and float(moved.mean()) < 1e-3 * extent
    dots = (gpu.model.quats.detach().cpu() * cpu.model.quats.detach()).sum(dim=1).abs()
    assert float(torch.quantile(dots, 0.01)) > 0.9995  # 2 acos(0.9995) = 3.6 degrees
    for i in range(len(cpu.views)):
        a = cpu.render_view(cpu.model, i, cpu.plan).rgb
        b = gpu.render_view(gpu.model, i, gpu.plan).rgb.cpu()
        assert float(psnr(b, a)) > 30.0, f"view {i}"
    assert abs(gpu.evaluate() - cpu.evaluate()) < 0.5  # both fit the frame as well


def test_the_frozen_stage_stays_bit_for_bit_on_cuda(setup):
    key = setup[3]
    moving = torch.zeros(len(key), dtype=torch.bool)
    moving[: len(key) // 2] = True
    tracker = _tracker(setup, "cuda", moving=moving)
    tracker.train()
    ids = tracker.ids.cpu()
    frozen_ids = torch.arange(len(key))[~moving]
    rows = torch.nonzero(torch.isin(ids, frozen_ids))[:, 0]
    assert len(rows) == len(frozen_ids)  # none pruned, none born
    order = ids[rows]
    for name, value in tracker.model.params.items():
        assert torch.equal(value.detach().cpu()[rows], key.params[name].detach()[order]), name
    live = torch.nonzero(~torch.isin(ids, frozen_ids))[:, 0]
    kept = live[ids[live] < len(key)]  # the moving Gaussians the key frame had
    shift = tracker.model.means.detach().cpu()[kept] - key.means.detach()[ids[kept]]
    assert float(shift.norm(dim=1).max()) > 0  # the subject did move


def test_a_short_sequence_reconstructs_on_cuda_and_carries_to_the_cpu(setup, tmp_path: Path):
    """Two frames on CUDA, packed after the first (`core.pipeline.carry`) and finished on the
    CPU: a run moves between machines, whatever their devices."""
    from core.pipeline import Stopped, reconstruct
    from core.pipeline.carry import pack_resume, unpack_resume

    capture = setup[0]
    overrides = {**RUN, "gop": 2, "train": {**RUN["train"], "device": "cuda"}}
    done: list[str] = []
    with pytest.raises(Stopped):
        reconstruct(capture.root, tmp_path / "gpu", preset="test", overrides=overrides,
                    progress=False, on_progress=lambda e: e.kind == "frame_done"
                    and done.append(e.frame), should_stop=lambda: bool(done))
    assert read_run(tmp_path / "gpu").config.train.device == "cuda:0"
    record = pack_resume(tmp_path / "gpu", tmp_path / "pack")
    assert record["next"] == "000001" and list(record["arrays"]) == ["000000"]
    unpack_resume(tmp_path / "pack", tmp_path / "cpu")
    metrics = reconstruct(capture.root, tmp_path / "cpu", preset="test", overrides=overrides,
                          progress=False, resume=True, device="cpu")
    assert list(metrics["frames"]) == ["000000", "000001"]
    assert (tmp_path / "cpu" / "frames" / "000001" / "gaussians.ply").is_file()
