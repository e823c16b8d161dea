"""Initial points: the capture's own cloud (points.ply from COLMAP points3D or a nerfstudio PLY),
points triangulated from the known poses, and random points only as the last resort."""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from core.data import import_capture, load_capture, validate_capture
from core.data.importers.colmap import export_colmap
from core.data.importers.transforms import export_transforms
from core.data.points import PointCloud, read_colmap_points, read_points_ply, write_points_ply
from core.config import InitConfig, train_config
from core.rig.hull import HULL_CONFIDENCE
from core.seeding import encloses, look_at_center, seed_points
from core.synth import SynthConfig, synthesize
from core.training import Trainer


@pytest.fixture(scope="module")
def textured(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """16 views of 160x160 of the figure: enough pixels on its checker texture for SIFT."""
    out = tmp_path_factory.mktemp("seeding") / "capture"
    synthesize(out, SynthConfig(frames=1, views=16, width=160, height=160, seed=2,
                                ao_directions=8))
    return out


def _cloud(n: int = 200, seed: int = 0) -> PointCloud:
    rng = np.random.default_rng(seed)
    return PointCloud(rng.normal(0, 0.3, (n, 3)) + [0, 0, 0.9],
                      rng.integers(0, 256, (n, 3)).astype(np.float32) / 255)


def test_points_ply_round_trip_binary_and_ascii(tmp_path: Path):
    cloud = _cloud()
    write_points_ply(tmp_path / "p.ply", cloud)
    back = read_points_ply(tmp_path / "p.ply")
    np.testing.assert_allclose(back.points, cloud.points, atol=1e-6)  # float32 in the file
    np.testing.assert_allclose(back.colors, cloud.colors, atol=1e-6)
    lines = ["ply", "format ascii 1.0", "comment from a scanner", "element vertex 2",
             "property double x", "property double y", "property double z",
             "property float nx", "property uchar red", "property uchar green",
             "property uchar blue", "element face 1", "property list uchar int vertex_indices",
             "end_header", "1 2 3 0 255 0 0", "4 5 6.5 1 0 128 255", "3 0 1 1"]
    (tmp_path / "a.ply").write_text("\n".join(lines) + "\n")
    ascii_cloud = read_points_ply(tmp_path / "a.ply")
    np.testing.assert_allclose(ascii_cloud.points, [[1, 2, 3], [4, 5, 6.5]])
    np.testing.assert_allclose(ascii_cloud.colors, [[1, 0, 0], [0, 128 / 255, 1]], atol=1e-6)


@pytest.mark.parametrize("text,words", [
    ("not a ply", "not a PLY"),
    ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
     "property float y\nproperty float z\nend_header\n", "truncated"),
    ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n"
     "1 2\n", "x, y and z"),
])
def test_bad_points_ply_is_named(tmp_path: Path, capture_copy: Path, text: str, words: str):
    (capture_copy / "points.ply").write_text(text)
    problems = validate_capture(capture_copy)
    assert len(problems) == 1 and problems[0].path.endswith("points.ply")
    assert words in problems[0].message, problems[0].message


@pytest.mark.parametrize("binary", [False, True], ids=["text", "binary"])
def test_colmap_points_seed_the_trainer(synth_capture: Path, tmp_path: Path, binary: bool):
    source = load_capture(synth_capture)
    one = type(source)(source.root, source.cameras, source.frames[:1], source.up)
    cloud = _cloud(300)
    model = export_colmap(one, tmp_path / "colmap", binary=binary, points=cloud)
    back = read_colmap_points(model)
    np.testing.assert_allclose(back.points, cloud.points, atol=1e-12)
    out = import_capture(tmp_path / "colmap", tmp_path / "imported")
    assert out.import_record["points"] == 300
    assert validate_capture(out.root) == []
    np.testing.assert_allclose(read_points_ply(out.points_path()).points, cloud.points,
                               atol=1e-6)
    # COLMAP carries no masks: every point seeds, plus a background shell of a tenth as many.
    cfg = replace(train_config("test"), init_points=400)
    trainer = Trainer.from_capture(out, out.frames[0], cfg)
    assert trainer.notes[0].startswith("seeded with 300 of the capture's 300 points + 30 "
                                       "background points"), trainer.notes[0]
    means = trainer.model.means.detach().double().numpy()
    np.testing.assert_allclose(means[:300], cloud.points, atol=1e-6)
    assert len(trainer.model) == 330


def test_masks_carve_capture_points_and_fill_the_hull(synth_capture: Path):
    from core.data.dataset import CaptureDataset

    cap = load_capture(synth_capture)
    ds = CaptureDataset(cap, frames=cap.frames[:1])
    views = [ds[i] for i in range(len(ds))]
    cams, masks = [v.camera for v in views], [v.mask.numpy() for v in views]
    cloud = _cloud(3000)
    seed = seed_points(cams, [v.image.numpy() for v in views], masks, InitConfig(),
                       n_random=1000, capture_points=cloud)
    kept = int(seed.note.split("seeded with ")[1].split(" ")[0])
    assert 32 < kept < 1000 and f"{1000 - kept} random points in the visual hull" in seed.note
    assert len(seed.points) == 1000 and "background" not in seed.note
    # Every seed lands on the foreground of every view it projects into.
    from core.triangulation import in_visual_hull

    assert in_visual_hull(seed.points.double().numpy(), cams, masks).all()


def test_nerfstudio_ply_file_path_becomes_points_ply(synth_capture: Path, tmp_path: Path):
    source = load_capture(synth_capture)
    one = type(source)(source.root, source.cameras, source.frames[:1], source.up)
    path = export_transforms(one, tmp_path / "ns")
    data = json.loads(path.read_text())
    data["ply_file_path"] = "sparse_pc.ply"
    path.write_text(json.dumps(data))
    write_points_ply(tmp_path / "ns" / "sparse_pc.ply", _cloud(50))
    out = import_capture(tmp_path / "ns", tmp_path / "out")
    assert len(read_points_ply(out.points_path())) == 50
    data["ply_file_path"] = "missing.ply"
    path.write_text(json.dumps(data))
    with pytest.raises(Exception, match="ply_file_path"):
        import_capture(tmp_path / "ns", tmp_path / "out2")


def test_triangulated_points_lie_on_the_surface(textured: Path):
    """Without a point cloud, SIFT matches between neighbouring cameras triangulated with the
    known projections land near the figure's true surface: median under 1.5% of its size (1-2
    pixels of localisation at this resolution), 90% within 3%, all within 6% (the worst are
    corners of the silhouette, which move with the view, as with any feature triangulation)."""
    from scipy.spatial import cKDTree

    import trimesh

    from core.data.dataset import CaptureDataset
    from core.training import training_cameras
    from core.triangulation import TriangulationConfig, triangulate_views

    cap = load_capture(textured)
    ds = CaptureDataset(cap, cameras=[c.id for c in training_cameras(cap)])
    views = [ds[i] for i in range(len(ds))]
    cloud, stats = triangulate_views([v.camera for v in views], [v.image.numpy() for v in views],
                                     [v.mask.numpy() for v in views])
    assert stats.points == len(cloud) >= 30, stats
    # Every point is seen twice or more, within the triangulator's reprojection bound.
    assert stats.observations >= 2 * stats.points, stats
    assert 0 < stats.reprojection < TriangulationConfig().max_reprojection, stats
    mesh = trimesh.load(textured / "gt" / "meshes" / "000000.ply")
    surface = trimesh.sample.sample_surface(mesh, 200_000, seed=0)[0]
    dist, _ = cKDTree(surface).query(cloud.points)
    size = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    assert np.median(dist) < 0.015 * size, np.median(dist) / size
    assert np.percentile(dist, 90) < 0.03 * size, np.percentile(dist, 90) / size
    assert dist.max() < 0.06 * size, dist.max() / size
    # Colours come from the images: the figure is not black.
    assert float(cloud.colors.mean()) > 0.05


def test_triangulation_seeds_a_capture_without_points(textured: Path):
    cfg = replace(train_config("test"), init_points=300)
    cfg = replace(cfg, init=replace(cfg.init, source="triangulate"))
    trainer = Trainer.from_capture(load_capture(textured), "000000", cfg)
    assert "triangulated from the known poses" in trainer.notes[0]
    assert "random points in the visual hull" in trainer.notes[0]
    assert len(trainer.model) == 300


def test_unmasked_views_get_a_background_shell_and_random_is_the_last_resort(textured: Path,
                                                                           caplog):
    from core.data.dataset import CaptureDataset

    cap = load_capture(textured)
    ds = CaptureDataset(cap, cameras=[c.id for c in cap.cameras[1:8]])
    views = [ds[i] for i in range(len(ds))]
    cams, images = [v.camera for v in views], [v.image.numpy() for v in views]
    # Cameras on one side see a far background; a studio's ring is inside its enclosure.
    side = [c for c in cap.cameras if c.center[0] > 1.0]  # six on the +x side
    assert len(side) == 6 and not encloses(side, look_at_center(side))
    assert encloses(cams, look_at_center(cams))
    # Seven around it (a studio's ring): the background is the enclosure they are mounted on,
    # at their distance, with at least background x init_points points.
    ring = seed_points(cams, images, [None] * len(cams), InitConfig(background=0.5),
                       n_random=100)
    assert "background points on the enclosure: a shell of radius 3.2" in ring.note
    look = torch.from_numpy(look_at_center(cams))
    dist = (ring.points.double() - look).norm(dim=-1)
    assert int(((dist - 3.2).abs() < 0.01).sum()) >= 50
    # Blank images: no feature, no point; random points with a warning.
    blank = [np.zeros_like(i) for i in images]
    with caplog.at_level(logging.WARNING, logger="dgs.seeding"):
        fallback = seed_points(cams, blank, [None] * len(cams), InitConfig(), n_random=100)
    assert "random points in the cameras' common view (a fallback: 0 points triangulated" \
        in fallback.note and len(fallback.points) == 100
    assert "random points" in caplog.text
    with pytest.raises(ValueError, match="triangulate"):
        seed_points(cams, blank, [None] * len(cams), InitConfig(source="triangulate"),
                    n_random=100)
    with pytest.raises(ValueError, match="points.ply"):
        seed_points(cams, images, [None] * len(cams), InitConfig(source="points"), n_random=10)
    with pytest.raises(ValueError, match="source"):
        InitConfig(source="lidar")
    rand = seed_points(cams, images, [None] * len(cams), InitConfig(source="random"),
                       n_random=64)
    assert len(rand.points) == 64 and torch.isfinite(rand.points).all()


def test_dense_seeds_from_the_rig_lie_on_the_surface(textured: Path):
    """Without a point cloud the seeds are the views' stereo depth fused across views: many
    more than triangulation finds, on the figure's true surface, inside the mattes' hull, and
    half the budget is left to random points in the hull (stereo misses thin parts)."""
    from scipy.spatial import cKDTree

    import trimesh

    from core.triangulation import in_visual_hull

    cfg = replace(train_config("test"), init_points=2000)
    trainer = Trainer.from_capture(load_capture(textured), "000000", cfg)
    note = trainer.notes[0]
    assert "points fused from the views' stereo depth" in note and \
        "1000 random points in the visual hull" in note, note
    fused = dict(trainer.seed.parts)["fused"]
    assert len(fused) == 1000 and trainer.seed.static is None
    available = int(note.split(" of ")[1].split(" ")[0])
    stats = trainer.rig.sparse()[1]
    assert available > 10 * stats.points, (available, stats.points)
    mesh = trimesh.load(textured / "gt" / "meshes" / "000000.ply")
    surface = trimesh.sample.sample_surface(mesh, 200_000, seed=0)[0]
    dist, _ = cKDTree(surface).query(fused.points)
    size = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    assert np.median(dist) < 0.01 * size and np.percentile(dist, 90) < 0.03 * size, \
        np.median(dist) / size
    assert in_visual_hull(fused.points, trainer.rig.cameras, trainer.rig.masks).all()
    assert trainer.seed_seconds > 0 and {"triangulation", "stereo"} <= set(trainer.rig.seconds)


def test_rig_priors_fill_views_without_priors(textured: Path):
    """The rig's priors go to views with none, with their confidence; a capture's own priors
    or an estimator come first."""
    from core.priors import fill_priors

    cfg = train_config("test")
    cap = load_capture(textured)
    trainer = Trainer.from_capture(cap, "000000", cfg)
    assert all(v.normal is None for v in trainer.views)
    assert fill_priors(trainer.views, None, trainer.rig) == "rig"
    gt = [np.load(textured / "gt" / "normals" / "000000" / f"{v.camera.id}.npy")
          for v in trainer.views]
    cos, cover, hull = [], [], []
    for v, truth in zip(trainer.views, gt):
        n, w = v.normal.numpy(), v.normal_weight.numpy()[..., 0]
        on = (np.linalg.norm(truth, axis=-1) > 0.5) & (w > 0)
        cover.append(on.sum() / (np.linalg.norm(truth, axis=-1) > 0.5).sum())
        cos.append(float((n * truth).sum(-1)[on].mean()))
        assert ((w > 0) <= (np.linalg.norm(n, axis=-1) > 0.5)).all()  # weight only on priors
        # Each prior says its source: stereo's measured, the hull's (the figure's mattes) not,
        # at the hull's confidence.
        measured = v.normal_measured.numpy()[..., 0]
        assert set(np.unique(measured)) <= {0.0, 1.0} and (measured <= (w > 0)).all()
        guessed = (measured == 0) & (w > 0)
        assert np.allclose(w[guessed], HULL_CONFIDENCE)
        hull.append(guessed.sum() / (w > 0).sum())
    assert np.mean(cover) > 0.8 and np.mean(cos) > 0.8, (np.mean(cover), np.mean(cos))
    assert 0 < np.mean(hull) < 1, np.mean(hull)  # both sources in use
    assert "priors" in trainer.rig.seconds
    # Off (no rig) the views keep no prior.
    fresh = Trainer.from_capture(cap, "000000", cfg)
    assert fill_priors(fresh.views, None, None) == "off" and fresh.views[0].normal is None


def test_no_seed_is_left_in_front_of_a_lens(textured: Path):
    """A seed just in front of a camera (a wall point by a camera mounted on it) would grow
    into a Gaussian over its whole view: seeds within CLEARANCE of any camera's distance, held-
    out cameras included (`clear_of`), are dropped."""
    from core.data.dataset import CaptureDataset
    from core.seeding import CLEARANCE

    cap = load_capture(textured)
    ds = CaptureDataset(cap, cameras=[c.id for c in cap.cameras[1:8]])
    views = [ds[i] for i in range(len(ds))]
    cams, images = [v.camera for v in views], [v.image.numpy() for v in views]
    held = cap.cameras[0]
    near = [c.center + 0.05 * c.R[2] for c in (cams[0], held)]  # 5 cm in front of two lenses
    cloud = _cloud(100)
    cloud = PointCloud(np.concatenate([cloud.points, near]),
                       np.concatenate([cloud.colors, np.full((2, 3), 0.5, np.float32)]))
    cfg = InitConfig(source="points", background=0)
    seed = seed_points(cams, images, [None] * len(cams), cfg, n_random=100,
                       capture_points=cloud, clear_of=[held])
    assert "(2 within 0.07 of a camera's distance dropped)" in seed.note, seed.note
    pts = seed.points.double().numpy()
    for c in [*cams, held]:
        reach = CLEARANCE * np.linalg.norm(c.center - look_at_center([*cams, held]))
        assert (np.linalg.norm(pts - c.center, axis=1) > reach).all()
    kept = seed_points(cams, images, [None] * len(cams), cfg, n_random=100,
                       capture_points=cloud)
    assert "(1 within" in kept.note  # without the held-out camera only its own lens is cleared


def test_sigterm_still_reaches_python_after_colmap_loads(tmp_path: Path):
    """COLMAP's logging takes SIGTERM when pycolmap loads (a stack trace, then death): a worker
    process that imported the triangulation must still run its own handler (checkpoint, give
    the job back), as a fresh interpreter shows."""
    import subprocess
    import sys

    code = ("import os, signal, sys\n"
            "seen = []\n"
            "signal.signal(signal.SIGTERM, lambda *a: seen.append(1))\n"
            "import core.triangulation\n"
            "os.kill(os.getpid(), signal.SIGTERM)\n"
            "signal.signal(signal.SIGTERM, lambda *a: seen.append(2))\n"
            "os.kill(os.getpid(), signal.SIGTERM)\n"
            "print(seen)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[2], timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[1, 2]", out.stderr[-2000:]
