"""A scene around a moving subject: the subject hull against hand-placed points, and a tracked
frame that moves only what is inside it while the rest of the scene stays bit for bit."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from core.config import SequenceConfig, load_config, select_views
from core.model import GaussianModel
from core.render import RenderCamera
from core.sequence.hull import dilate, inside_hull

TINY = {"train": {"schedule": {"iterations": 40, "stage2_start": 12, "stage3_start": 28,
                               "densify_from": 2, "densify_until": 24, "densify_interval": 5,
                               "reset_interval": 15, "sh_interval": 5},
                  "init_points": 300},
        "sequence": {"num_nodes": 64, "deform_fraction": 0.25, "refine_fraction": 0.25},
        "gop": 3}


def _camera(z: float = 0.0) -> RenderCamera:
    """A 20x10 camera at the origin looking down +z (OpenCV axes), focal 10."""
    viewmat = torch.eye(4)
    viewmat[2, 3] = z
    K = torch.tensor([[10.0, 0, 10.0], [0, 10.0, 5.0], [0, 0, 1]])
    return RenderCamera(viewmat, K, 20, 10)


def test_dilate_grows_by_whole_pixels():
    m = torch.zeros(9, 9, 1)
    m[4, 4] = 1
    assert int(dilate(m, 1).sum()) == 9 and int(dilate(m, 2).sum()) == 25
    assert dilate(m, 0) is m


def test_inside_hull_by_hand():
    cam = _camera()
    mask = torch.zeros(10, 20, 1)
    mask[:, :10] = 1  # the left half
    pts = torch.tensor([[-0.5, 0.0, 1.0],   # u = 5: inside
                        [0.5, 0.0, 1.0],    # u = 15: outside
                        [0.05, 0.0, 1.0],   # u = 10.5: outside, but within 1 px of the mask
                        [0.0, 0.0, -1.0]])  # behind the camera: seen by no view
    assert inside_hull(pts, [cam], [mask], dilate_pixels=0).tolist() == [True, False, False,
                                                                        False]
    assert inside_hull(pts, [cam], [mask], dilate_pixels=1).tolist() == [True, False, True,
                                                                        False]
    # Two views: inside one of the two passes share 0.5, not 0.8; a view without a mask does
    # not vote.
    empty = torch.zeros(10, 20, 1)
    assert inside_hull(pts[:1], [cam, cam], [mask, empty], share=0.5).tolist() == [True]
    assert inside_hull(pts[:1], [cam, cam], [mask, empty], share=0.8).tolist() == [False]
    assert inside_hull(pts[:1], [cam, cam], [mask, None], share=0.8).tolist() == [True]
    with pytest.raises(ValueError, match="one per camera"):
        inside_hull(pts, [cam], [])


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny synthetic sequence whose masks mark the subject in a picture kept whole."""
    from core.synth import SynthConfig, synthesize

    out = tmp_path_factory.mktemp("scene") / "capture"
    synthesize(out, SynthConfig(frames=2, views=8, width=32, height=32, seed=4, priors=True,
                                ao_directions=8))
    data = json.loads((out / "capture.json").read_text())
    data["masks"] = "subject"
    (out / "capture.json").write_text(json.dumps(data))
    return out


def test_a_tracked_frame_moves_the_subject_and_leaves_the_scene(scene: Path, tmp_path: Path,
                                                                 one_thread) -> None:
    from core.data import load_capture
    from core.pipeline import reconstruct
    from core.sequence import FrameTracker, load_frame
    from core.sequence.tracks import moves_subject, subject_rows
    from core.training import frame_views

    run = tmp_path / "run"
    reconstruct(scene, run, preset="test", overrides=TINY, progress=False, frames="0:1")
    model, ids = load_frame(run / "frames" / "000000" / "gaussians.ply")
    # A backdrop that no mask covers: 40 Gaussians on a far ring behind the subject.
    params = {k: v.detach().clone() for k, v in model.params.items()}
    far = params["means"].mean(0) + torch.randn(40, 3, generator=torch.Generator()
                                                .manual_seed(0)) * 0.1 + torch.tensor(
        [0.0, 0.0, 30.0])
    params = {k: torch.cat([v, v[:40].clone()]) for k, v in params.items()}
    params["means"][-40:] = far
    model = GaussianModel(params)
    ids = torch.cat([ids, torch.arange(len(ids), len(ids) + 40)])

    capture = load_capture(scene)
    cfg = load_config("test", overrides=TINY)
    views = select_views(capture, masks=cfg.train.masks)
    assert views.subject and moves_subject(views, cfg.sequence)
    assert not moves_subject(views, SequenceConfig(moving="all"))
    views = frame_views(capture, "000001")
    assert views[0].mask is None and views[0].subject is not None  # the picture kept whole
    moving = subject_rows(model.means, [views, frame_views(capture, "000000")], cfg.sequence)
    assert not bool(moving[-40:].any()) and int(moving.sum()) > 20

    tracker = FrameTracker(views, model, ids, 10 ** 6, cfg.train, cfg.sequence, moving=moving)
    tracker.train()
    out, frozen, out_ids = tracker.model, tracker.state.frozen, tracker.state.ids
    assert int(frozen.sum()) == int((~moving).sum())  # none of them pruned or densified
    before = {name: p.detach() for name, p in model.params.items()}
    rows = {int(i): r for r, i in enumerate(ids.tolist())}
    old = torch.tensor([rows[int(i)] for i in out_ids[frozen]])
    for name, p in out.params.items():
        assert torch.equal(p.detach()[frozen], before[name][old]), name
    # The subject moved (deformed and refined), and only it was densified.
    kept = torch.tensor([rows.get(int(i), -1) for i in out_ids[~frozen]])
    known = kept >= 0
    assert not torch.equal(out.means.detach()[~frozen][known], before["means"][kept[known]])


def test_the_subject_export_keeps_the_hull(scene: Path, tmp_path: Path, one_thread) -> None:
    from core.export.run import export_run
    from core.pipeline import reconstruct

    run = tmp_path / "run"
    reconstruct(scene, run, preset="test", overrides=TINY, progress=False)
    whole = export_run(run, tmp_path / "whole", formats=["ply", "stream"])
    subject = export_run(run, tmp_path / "subject", formats=["ply", "stream"], subject=True)
    assert 0 < subject["subject"]["share"] <= 1
    assert subject["ply_bytes_per_frame"] <= whole["ply_bytes_per_frame"]
    assert subject["stream"]["bytes"] <= whole["stream"]["bytes"]
    # The group keeps one set of track ids in every frame: a Gaussian of the key frame kept in
    # the second frame is kept in the key frame too.
    from core.export.splats import read_frame_ply

    a, b = (read_frame_ply(tmp_path / "subject" / "ply" / f"{f}.ply") for f in
            ("000000", "000001"))
    key = read_frame_ply(run / "frames" / "000000" / "gaussians.ply")
    assert 0 < len(a) < len(key) or subject["subject"]["share"] == 1
    assert set(b.ids.tolist()) & set(key.ids.tolist()) <= set(a.ids.tolist())


def test_a_later_key_frame_keeps_the_static_seeds(tmp_path: Path, one_thread) -> None:
    """Every frame a key frame (groups of 1): the second seeds its subject from its own views'
    depth and keeps the first key frame's static scene (RUN/seeds/static.ply); a part of the
    job that runs the second group alone makes the same static seeds and the same frame."""
    from core.data.points import read_points_ply
    from core.pipeline import reconstruct
    from core.synth import SynthConfig, synthesize

    scene = tmp_path / "capture"  # 64 pixels: enough for stereo (32 gives it nothing)
    synthesize(scene, SynthConfig(frames=2, views=10, width=64, height=64, seed=4,
                                  ao_directions=8))
    data = json.loads((scene / "capture.json").read_text())
    data["masks"] = "subject"
    (scene / "capture.json").write_text(json.dumps(data))

    over = {**TINY, "gop": 1}
    whole = tmp_path / "whole"
    metrics = reconstruct(scene, whole, preset="test", overrides=over, progress=False,
                          frames="0:2")
    first, second = (metrics["frames"][f]["notes"][0] for f in ("000000", "000001"))
    assert "points fused from the views' stereo depth" in first and "background" in first
    static = read_points_ply(whole / "seeds" / "static.ply")
    assert f"seeded with {len(static)} static-scene points kept from the first key frame" \
        in second and "subject points fused from this frame's stereo depth" in second
    assert (whole / "plots" / "seeds-000001.png").is_file()
    assert metrics["frames"]["000001"]["seed_seconds"] > 0
    part = tmp_path / "part"
    reconstruct(scene, part, preset="test", overrides=over, progress=False, frames="0:2",
                gops={1})
    assert not (part / "frames" / "000000").exists()
    assert (part / "seeds" / "static.ply").read_bytes() == \
        (whole / "seeds" / "static.ply").read_bytes()
    assert (part / "frames" / "000001" / "gaussians.ply").read_bytes() == \
        (whole / "frames" / "000001" / "gaussians.ply").read_bytes()
