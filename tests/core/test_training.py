"""The trainer: seeding from a capture, stage transitions and hooks, and the `test` preset end to
end on a tiny synthetic capture (loss goes down, PSNR on training views goes up)."""

from __future__ import annotations

import io
import math
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from core.config import Schedule, train_config
from core.data import CaptureDataset, load_capture
from core.model import GaussianModel
from core.seeding import look_at_center, sample_points, scene_extent
from core.synth import SynthConfig, synthesize
from core.training import (
    CheckpointCallback,
    ProgressCallback,
    Trainer,
    View,
    training_cameras,
)


@pytest.fixture(scope="module")
def tiny_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """8 views of 32x32, one frame, with masks and normal priors."""
    out = tmp_path_factory.mktemp("train") / "capture"
    synthesize(out, SynthConfig(frames=1, views=8, width=32, height=32, seed=1, priors=True,
                                ao_directions=8))
    return out


@pytest.fixture(scope="module")
def views(tiny_capture: Path) -> list[View]:
    cap = load_capture(tiny_capture)
    cams = training_cameras(cap)
    ds = CaptureDataset(cap, frames=[cap.frames[0]], cameras=[c.id for c in cams])
    return [View.from_sample(ds[i]) for i in range(len(ds))]


def test_presets_resolve_to_json():
    for name in ("paper", "fast", "test"):
        cfg = train_config(name)
        data = json.loads(json.dumps(cfg.to_dict()))
        assert data["schedule"]["iterations"] == cfg.schedule.iterations
        assert data["eps2d"] == 0.1 and data["antialiased"] is True
    assert train_config("paper").schedule.iterations == 30_000
    assert train_config("test").densify.max_gaussians == 4_000
    with pytest.raises(ValueError, match="preset"):
        train_config("huge")
    with pytest.raises(ValueError, match="init_points"):
        replace(train_config("test"), init_points=0)


def test_training_cameras_hold_out_every_eighth(tiny_capture: Path):
    cap = load_capture(tiny_capture)
    ids = [c.id for c in training_cameras(cap)]
    assert len(ids) == 7 and cap.cameras[0].id not in ids


def test_from_capture_uses_the_training_cameras(tiny_capture: Path):
    cap = load_capture(tiny_capture)
    trainer = Trainer.from_capture(cap, cap.frames[0], replace(train_config("test"),
                                                                init_points=50))
    assert [v.camera.id for v in trainer.views] == [c.id for c in cap.cameras[1:]]
    assert trainer.views[0].mask is not None and trainer.views[0].normal is not None
    assert len(trainer.model) == 50
    with pytest.raises(ValueError, match="frame"):
        Trainer.from_capture(cap, "999999")


def test_every_render_of_a_trainer_clips_at_its_near_plane(views: list[View]):
    from core.ao import scaled_camera
    from core.data.layout import near_plane

    model = GaussianModel.from_points(torch.zeros(4, 3), torch.full((4, 3), 0.5))
    given = Trainer(views, replace(train_config("test"), near=0.3), model=model)
    assert given.near == 0.3 and all(c.near == 0.3 for c in given.cameras)
    assert scaled_camera(given.cameras[0], 0.25).near == 0.3  # the AO bake's cameras too
    rig = Trainer(views, train_config("test"), model=model)  # a config resolved with no run
    assert rig.near == pytest.approx(near_plane([v.camera for v in views]))
    assert rig.cameras[0].near == rig.near and 0.01 < rig.near


def test_seeding_lands_in_the_visual_hull(views: list[View]):
    cams = [v.camera for v in views]
    center = look_at_center(cams)
    np.testing.assert_allclose(center, [0.0, 0.0, 0.9], atol=0.05)  # the synth look-at target
    assert 3.0 < scene_extent(cams) < 4.5  # cameras on a 3.2 m dome
    masks = [v.mask.numpy() for v in views]
    pts, cols = sample_points(cams, 300, images=[v.image.numpy() for v in views], masks=masks,
                              seed=0)
    assert pts.shape == (300, 3) and cols.shape == (300, 3)
    for cam, mask in zip(cams, masks):
        uv, z = cam.project(pts.numpy().astype(np.float64))
        assert np.all(z > 0)
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        assert np.all(mask[v, u, 0] > 0.5)
    assert float(cols.mean()) > 0.05  # coloured from the (non-black) figure
    with pytest.raises(ValueError, match="masks"):
        sample_points(cams, 10, masks=[np.zeros_like(m) for m in masks], max_rounds=2)


class FakeBaker:
    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, model: GaussianModel, cameras, optimizer=None, beta: float = 0.0):
        self.calls += 1
        return [torch.full((c.height, c.width, 1), 0.8) for c in cameras]


def test_stage_transitions_and_ao_hook(views: list[View], one_thread):
    schedule = Schedule(iterations=12, stage2_start=4, stage3_start=8, sh_interval=1,
                        densify_from=1, densify_until=10, densify_interval=3, reset_interval=5,
                        densify_epoch=False)
    cfg = replace(train_config("test"), schedule=schedule, init_points=200)
    baker = FakeBaker()
    seen = []
    trainer = Trainer(views, cfg, ao_baker=baker,
                      callbacks=[ProgressCallback(every=1, report=seen.append)])
    trainer.train()
    assert [i.plan.stage for i in seen] == [1] * 4 + [2] * 4 + [3] * 4
    assert baker.calls == 1 and trainer.ao_targets is not None
    assert [n.split(" ")[0] for n in trainer.notes] == ["seeded"]  # no note of a skipped bake
    assert all("visibility" in i.losses for i in seen[8:])
    assert not any("visibility" in i.losses for i in seen[:8])
    assert all({"normal", "consistency", "mask"} <= set(i.losses) for i in seen[4:])
    assert all(set(i.losses) == {"photometric", "total"} for i in seen[:4])
    # Stage 2 untied the geometry opacity and turned the normals to the shortest axes.
    assert not torch.equal(trainer.model.params["opacity_g"], trainer.model.params["opacity_c"])
    assert trainer.model.normals[:, 2].abs().min() < 0.99
    assert seen[-1].plan.sh_degree == 3 and seen[-1].plan.beta == pytest.approx(0.7)
    # One reset (step 5; step 10 is not < densify_until), densifications at 3, 6 and 9.
    assert trainer.state.resets == 1
    assert sum("pruned" in h for h in trainer.state.history) == 1
    assert sum("cloned" in h for h in trainer.state.history) == 3


def test_test_preset_end_to_end(views: list[View], tmp_path: Path, one_thread):
    cfg = train_config("test")
    lines = io.StringIO()
    seen = []
    trainer = Trainer(views, cfg, callbacks=[
        ProgressCallback(every=1, report=seen.append), ProgressCallback(every=100, stream=lines),
        CheckpointCallback(tmp_path / "ckpt", every=250)])
    psnr_before = trainer.evaluate()
    trainer.train()
    psnr_after = trainer.evaluate()
    photo = [i.losses["photometric"] for i in seen]
    first, last = np.mean(photo[:25]), np.mean(photo[-25:])
    assert len(seen) == cfg.schedule.iterations
    assert last < 0.7 * first, (first, last)
    assert psnr_after > psnr_before + 3.0, (psnr_before, psnr_after)
    # AO was baked at the stage-3 step (native ray tracer) and the visibility loss ran after it.
    assert [n.split(" ")[0] for n in trainer.notes] == ["seeded"]
    assert trainer.ao_targets is not None and len(trainer.ao_targets) == len(views)
    assert all(0.0 <= float(t.min()) and float(t.max()) <= 1.0 for t in trainer.ao_targets)
    assert "visibility" in seen[-1].losses
    # initialised per Gaussian, not constant
    assert float(trainer.model.visibility.detach().std()) > 0
    assert len(lines.getvalue().splitlines()) == 6  # steps 1, 101, ..., 401 and the last
    assert len(trainer.model) > cfg.init_points  # densification ran
    assert len(trainer.model) <= cfg.densify.max_gaussians  # each densified one adds one row
    # Checkpoint round trip: the model and the step come back.
    resumed = Trainer(views, cfg, model=trainer.model)
    resumed.load_checkpoint(tmp_path / "ckpt" / "checkpoint.pt")
    assert resumed.step == cfg.schedule.iterations and len(resumed.model) == len(trainer.model)
    for name, p in trainer.model.params.items():
        assert torch.equal(resumed.model.params[name], p.detach())
    trainer.model.save_ply(tmp_path / "gaussians.ply")
    back = GaussianModel.load_ply(tmp_path / "gaussians.ply")
    assert torch.equal(back.params["means"], trainer.model.params["means"].detach())
    print(f"test preset: PSNR {psnr_before:.2f} -> {psnr_after:.2f} dB, photometric "
          f"{first:.4f} -> {last:.4f}, {len(trainer.model)} Gaussians")


def test_resume_repeats_the_uninterrupted_run_exactly(views: list[View], tmp_path: Path,
                                                      one_thread):
    """A checkpoint taken mid-epoch, after densifications that drew split samples, restores the
    random generator and the pending view order: the resumed run ends bit-identical."""
    schedule = Schedule(iterations=40, stage2_start=12, stage3_start=30, densify_from=2,
                        densify_until=28, densify_interval=4, reset_interval=15, sh_interval=3)
    cfg = replace(train_config("test"), schedule=schedule, init_points=300)
    straight = Trainer(views, cfg)
    straight.train()
    first = Trainer(views, cfg)
    for _ in range(17):  # 17 = 2 epochs of 7 views + 3: four views of this epoch still pending
        first.train_step()
    assert len(first._order) == 4 and any(h.get("split") for h in first.state.history)
    first.save_checkpoint(tmp_path / "ckpt.pt")
    first.train_step()  # the killed run went on a little; none of that may leak into the resume
    resumed = Trainer(views, cfg)
    resumed.load_checkpoint(tmp_path / "ckpt.pt")
    assert resumed.step == 17
    resumed.train()
    assert resumed.state.history == straight.state.history
    for name, p in straight.model.params.items():
        assert torch.equal(resumed.model.params[name], p), name


def test_random_background_makes_background_coloured_coverage_cost(views: list[View],
                                                                   one_thread):
    """A black opaque wall over the whole view matches a black background exactly where the mask
    says background (a floater that costs nothing); in front of the random colour of a step it
    does not. Views without a mask keep the configured background."""
    from core.model import SH_C0
    from core.stages import plan

    cfg = replace(train_config("test"), init_points=50)
    trainer = Trainer(views, cfg, ao_baker=FakeBaker())
    with torch.no_grad():
        trainer.model.params["sh0"].fill_(-0.5 / SH_C0)  # colour 0
        trainer.model.params["opacity_c"].fill_(9.0)
        trainer.model.params["scales"].fill_(math.log(3.0))
    p = plan(0, cfg.schedule)
    background = views[0].mask[..., 0] == 0
    black = torch.zeros(3)
    wall = trainer.render_view(trainer.model, 0, p, black).rgb.detach()
    assert float((wall - trainer.target(0, black))[background].abs().max()) < 1e-3
    colours = [trainer.step_background(0) for _ in range(2)]
    assert not torch.equal(colours[0], colours[1])  # a new colour every step
    bg = colours[0]
    target = trainer.target(0, bg)
    torch.testing.assert_close(target[background], bg.expand_as(target[background]))
    error = (trainer.render_view(trainer.model, 0, p, bg).rgb - target)[background].abs().mean(dim=0)
    torch.testing.assert_close(error, bg, atol=0.01, rtol=0)  # the wall shows black over bg
    unmasked = Trainer([View(views[0].camera, views[0].image)], cfg, ao_baker=FakeBaker())
    assert torch.equal(unmasked.step_background(0), torch.zeros(3))
    fixed = Trainer(views, replace(cfg, random_background=False), ao_baker=FakeBaker())
    assert torch.equal(fixed.step_background(0), torch.zeros(3))


def test_sparsity_regularizers_fade_and_shrink_the_gaussians(views: list[View], one_thread):
    """With 3DGS-MCMC's opacity and scale regularizers (`losses.opacity_l1`, `scale_l1`) a
    key frame ends with lower mean opacities and scales than the same run without them, the
    term is in the step's losses, and off (the default) it is not."""
    base = replace(train_config("test"), bake_ao=False)
    seen: list = []
    plain = Trainer(views, base, callbacks=[ProgressCallback(every=1, report=seen.append)])
    plain.train()
    assert all("sparsity" not in i.losses for i in seen)
    cfg = replace(base, losses=replace(base.losses, opacity_l1=0.05, scale_l1=0.5))
    seen = []
    sparse = Trainer(views, cfg, callbacks=[ProgressCallback(every=1, report=seen.append)])
    sparse.train()
    assert all("sparsity" in i.losses for i in seen)
    for name in ("opacity_c", "opacity_g", "scales"):
        a = float(getattr(plain.model, name).detach().mean())
        b = float(getattr(sparse.model, name).detach().mean())
        assert b < a, (name, a, b)


def test_densifications_are_an_epoch_apart(views: list[View]):
    """`densify_epoch` (the default) raises a scaled schedule's interval to the number of
    training views: every view is drawn once between two densifications; off, or with a
    longer interval, the schedule is kept."""
    sched = train_config("test").schedule
    assert sched.densify_epoch and sched.densify_interval < len(views)
    trainer = Trainer(views, train_config("test"))
    assert trainer.schedule.densify_interval == len(views)
    steps = [s for s in range(sched.iterations) if trainer.plan_at(s).densify]
    assert steps and all(s % len(views) == 0 for s in steps)
    assert sched.for_views(1) is sched
    off = replace(sched, densify_epoch=False)
    assert off.for_views(len(views)) is off
    with pytest.raises(ValueError, match="views"):
        sched.for_views(0)


def test_a_key_frame_relocates_its_transparent_gaussians(views: list[View], one_thread):
    """`densify.relocate` in a key frame: Gaussians the opacity regularizer fades are moved at
    densifications (the history says how many), and the key frame still learns its views."""
    base = replace(train_config("test"), bake_ao=False)
    cfg = replace(base, losses=replace(base.losses, opacity_l1=0.05),
                  densify=replace(base.densify, relocate=True))
    trainer = Trainer(views, cfg)
    before = trainer.evaluate()
    trainer.train()
    moved = [h["relocated"] for h in trainer.state.history if "relocated" in h]
    assert moved and sum(moved) > 0
    assert trainer.evaluate() > before + 3.0
