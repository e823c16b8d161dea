"""The training dataset: tensors, conventions, downscaling, undistortion, the memory bound."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from core.data import ByteLRUCache, CaptureDataset, load_capture
from core.data.images import write_png


def test_serves_views_as_tensors(synth_capture: Path) -> None:
    cap = load_capture(synth_capture)
    ds = CaptureDataset(cap)
    assert len(ds) == 16
    s = ds[ds.index_of("000001", "cam05")]
    assert (s.frame, s.camera_id) == ("000001", "cam05")
    assert s.image.shape == (48, 48, 3) and s.image.dtype == torch.float32
    assert 0.0 <= float(s.image.min()) and float(s.image.max()) <= 1.0
    # Masks are coverage: 0 off the figure, 1 inside, fractions on its silhouette.
    m = s.mask[:, :, 0]
    assert s.mask.shape == (48, 48, 1) and float(m.min()) == 0.0 and float(m.max()) == 1.0
    assert bool(((m > 0) & (m < 1)).any())
    # Priors are world-space unit vectors where the pixel centre is on the figure, zero where
    # nothing of the figure is.
    norms = s.normal.norm(dim=2)
    fg = torch.from_numpy(np.load(synth_capture / "gt/depth/000001/cam05.npy") > 0)
    assert torch.allclose(norms[fg], torch.ones(()), atol=1e-4)
    assert float(norms[m == 0].max()) == 0.0
    gt = np.load(synth_capture / "gt/normals/000001/cam05.npy")
    cos = (s.normal.numpy() * gt).sum(axis=2)[fg.numpy()]
    assert 0.8 < float(np.median(cos)) < 0.9999  # close to truth, but degraded
    with pytest.raises(IndexError):
        ds[16]


def test_downscale_scales_intrinsics(synth_capture: Path) -> None:
    cap = load_capture(synth_capture)
    s = CaptureDataset(cap, downscale=2)[3]
    cam = cap.cameras[3]
    assert s.image.shape == (24, 24, 3) and s.mask.shape == (24, 24, 1)
    np.testing.assert_allclose(s.camera.K[:2], cam.K[:2] / 2)
    # A 3D point lands on the same relative image position at both scales.
    point = np.array([[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(s.camera.project(point)[0], cam.project(point)[0] / 2, atol=1e-9)


def test_downscale_keeps_straight_colour(tmp_path: Path) -> None:
    """Image in straight colour with a coverage mask: after area downscaling, image * mask is
    still the area average of the premultiplied colour, and the served colour of an edge pixel is
    the foreground's alone (the black beside it does not darken it)."""
    from core.data import Camera, Capture, save_capture

    K = np.array([[8.0, 0, 4.0], [0, 8.0, 4.0], [0, 0, 1]])
    cam = Camera("c0", 8, 8, K, np.eye(4), None)
    rng = np.random.default_rng(0)
    image = rng.integers(40, 255, size=(8, 8, 3)).astype(np.uint8)
    mask = np.zeros((8, 8), np.uint8)
    mask[:, :3] = 255
    mask[:, 3] = 102  # 0.4 coverage
    image[mask == 0] = 0
    write_png(tmp_path / "cap/images/f0/c0.png", image)
    write_png(tmp_path / "cap/masks/f0/c0.png", mask)
    save_capture(Capture(tmp_path / "cap", (cam,), ("f0",), (0, -1, 0)))
    s = CaptureDataset(load_capture(tmp_path / "cap"), downscale=2)[0]
    c, a = image / 255.0, mask[:, :, None] / 255.0
    pre = (c * a).reshape(4, 2, 4, 2, 3).mean(axis=(1, 3))
    cover = a.reshape(4, 2, 4, 2, 1).mean(axis=(1, 3))
    np.testing.assert_allclose(s.mask.numpy(), cover, atol=1e-6)
    np.testing.assert_allclose((s.image * s.mask).numpy(), pre, atol=1e-5)
    straight = c[:, 2:4].reshape(4, 2, 2, 3) * a[:, 2:4].reshape(4, 2, 2, 1)
    edge = straight.sum(axis=(1, 2)) / a[:, 2:4].reshape(4, 4).sum(axis=1)[:, None]
    np.testing.assert_allclose(s.image[:, 1].numpy(), edge, atol=1e-5)


def test_memory_bound(synth_capture: Path) -> None:
    cap = load_capture(synth_capture)
    per_view = 48 * 48 * (3 + 1 + 3) * 4
    bound = int(per_view * 3.5)
    ds = CaptureDataset(cap, cache_bytes=bound)
    for _ in range(2):
        for i in range(len(ds)):
            ds[i]
            assert ds.cache.nbytes <= bound
    assert len(ds.cache) == 3 and ds.cache.nbytes == 3 * per_view
    assert ds.cache.misses == 2 * len(ds)  # 16 views cycled through 3 slots: no reuse possible
    ds[len(ds) - 1]
    assert ds.cache.hits == 1
    # A budget of zero still serves every view, caching nothing.
    empty = CaptureDataset(cap, cache_bytes=0)
    assert empty[5].image.shape == (48, 48, 3) and empty.cache.nbytes == 0


def test_lru_order() -> None:
    cache = ByteLRUCache(300)
    for key in "abc":
        cache.put(key, key, 100)
    cache.get("a")
    cache.put("d", "d", 100)  # evicts b, the least recently used
    assert cache.get("b") is None and cache.get("a") == "a" and cache.nbytes == 300
    cache.put("huge", "x", 301)
    assert cache.get("huge") is None and cache.nbytes == 300


def test_undistortion_moves_features_to_pinhole_position(tmp_path: Path) -> None:
    """Draw a dot where the distorted camera sees a point; after undistortion it sits where the
    ideal pinhole projects it."""
    from core.data import Camera, Capture, save_capture

    W, H = 80, 60
    K = np.array([[60.0, 0, 40.0], [0, 60.0, 30.0], [0, 0, 1]])
    dist = (-0.35, 0.05, 0.002, -0.001, 0.0)
    cam = Camera("c0", W, H, K, np.eye(4), dist)
    point = np.array([[0.5, 0.35, 1.0]])  # far from the centre, where distortion is strong
    distorted = cam.project(point)[0][0]
    ideal = Camera("c0", W, H, K, np.eye(4), None).project(point)[0][0]
    assert np.linalg.norm(distorted - ideal) > 3.0
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    blob = np.exp(-((xx - distorted[0]) ** 2 + (yy - distorted[1]) ** 2) / (2 * 1.5**2))
    write_png(
        tmp_path / "cap/images/f0/c0.png",
        (np.repeat(blob[:, :, None], 3, 2) * 255).astype(np.uint8),
    )
    save_capture(Capture(tmp_path / "cap", (cam,), ("f0",), (0, -1, 0)))
    s = CaptureDataset(load_capture(tmp_path / "cap"))[0]
    assert s.camera.distortion is None
    # Barrel distortion (k1 < 0): every ideal pixel samples inside the source, nothing is
    # cropped (pincushion crops: the next test); a crop would move the principal point only.
    x0, y0 = K[0, 2] - s.camera.K[0, 2], K[1, 2] - s.camera.K[1, 2]
    assert (s.camera.width, s.camera.height) == tuple(s.image.shape[1::-1]) == (W, H)
    assert x0 == y0 == 0 and s.camera.K[0, 0] == K[0, 0]
    img = s.image[:, :, 0].numpy()
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]] + 0.5
    centroid = np.array([(img * xx).sum(), (img * yy).sum()]) / img.sum()
    assert np.linalg.norm(centroid + [x0, y0] - ideal) < 0.3, (centroid, ideal, distorted)
    assert np.allclose(s.camera.project(point)[0][0], ideal - [x0, y0])
    raw = CaptureDataset(load_capture(tmp_path / "cap"), undistort=False)[0]
    assert raw.camera.distortion == dist


def test_undistorted_views_have_no_rim_from_outside_the_source(tmp_path: Path) -> None:
    """A white image seen through strong distortion: after undistortion and downscaling every
    served pixel is white (no black rim from samples outside the source, which a model cannot
    fit and which dominated the fox's held-out error)."""
    from core.data import Camera, Capture, save_capture

    W, H = 96, 64
    K = np.array([[70.0, 0, 48.0], [0, 70.0, 32.0], [0, 0, 1]])
    for k1 in (-0.3, 0.2):  # barrel, pincushion (which samples outside the source: cropped)
        cam = Camera("c0", W, H, K, np.eye(4), (k1, 0.02, 0.001, 0.0, 0.0))
        root = tmp_path / f"cap{k1}"
        write_png(root / "images/f0/c0.png", np.full((H, W, 3), 255, np.uint8))
        save_capture(Capture(root, (cam,), ("f0",), (0, -1, 0)))
        for downscale in (1.0, 2.0):
            s = CaptureDataset(load_capture(root), downscale=downscale)[0]
            assert float(s.image.min()) > 0.999, (k1, downscale)
            assert s.image.shape[1] * s.image.shape[0] > 0.5 * W * H / downscale**2
            if k1 > 0 and downscale == 1.0:
                assert s.image.shape[1] < W and s.image.shape[0] < H
                assert (s.camera.width, s.camera.height) == tuple(s.image.shape[1::-1])


def test_camera_space_normals_are_rotated_to_world(synth_capture: Path, tmp_path: Path) -> None:
    import shutil

    root = tmp_path / "cap"
    shutil.copytree(synth_capture, root, ignore=shutil.ignore_patterns("gt"))
    cap = load_capture(root)
    cam = cap.cameras[2]
    n_world = np.array([0.0, 0.6, 0.8])
    n_cam = cam.R @ n_world
    write_png(
        root / "normals/000000/cam02.png",
        np.full((48, 48, 3), 0, np.uint16) + ((n_cam + 1) / 2 * 65535).round().astype(np.uint16),
    )
    data = json.loads((root / "capture.json").read_text())
    data["normals_space"] = "camera"
    (root / "capture.json").write_text(json.dumps(data))
    s = CaptureDataset(load_capture(root))[2]
    np.testing.assert_allclose(s.normal[10, 10].numpy(), n_world, atol=1e-4)


def test_exr_images_and_normals_stay_linear(tmp_path: Path) -> None:
    from core.data import Camera, Capture, save_capture, validate_capture
    from core.data.images import write_exr

    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    cam = Camera("c0", 16, 12, K, np.eye(4), None)
    image = np.full((12, 16, 3), 2.5, np.float32)  # HDR value above 1 must survive
    normal = np.zeros((12, 16, 3), np.float32)
    normal[..., 2] = -1.0
    write_exr(tmp_path / "cap/images/f0/c0.exr", image)
    write_exr(tmp_path / "cap/normals/f0/c0.exr", normal)
    save_capture(Capture(tmp_path / "cap", (cam,), ("f0",), (0, -1, 0)))
    assert validate_capture(tmp_path / "cap") == []
    s = CaptureDataset(load_capture(tmp_path / "cap"))[0]
    assert float(s.image.min()) == 2.5 and s.mask is None
    np.testing.assert_allclose(s.normal[3, 4].numpy(), [0, 0, -1])
