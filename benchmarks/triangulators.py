"""Sparse points from known poses (issue 39): our SIFT triangulation (`core.triangulation`)
against COLMAP's point triangulator (pycolmap) on the same views.

- **ours**: `triangulate_views` as the project ships it (OpenCV SIFT, epipolar-guided
  matching between the `camera_pairs` neighbours, COLMAP's point triangulator with the poses
  fixed, visual hull). Until commit a4ecb95 its tracks and points were our own (connected
  components, DLT with reprojection and angle checks); the benchmark at commit efdfd8c measured
  that code as **ours** and COLMAP's triangulator on our matches as **colmap-ours**
  (docs/decisions/2026-11-29-sparse-points-pycolmap-or-ours.md).
- **colmap**: pycolmap with the capture's cameras (PINHOLE) and world-to-camera poses fixed:
  COLMAP SIFT (`extract_features`, masks as COLMAP masks) into a database, matching of the
  same neighbour pairs (`match_image_pairs`: ratio test and cross check over the whole image,
  RANSAC two-view verification), then `triangulate_points` (the incremental triangulator and
  bundle adjustment of the points with the poses constant), carved by the same visual hull.
- **colmap-guided**: as colmap, the RANSAC verification replaced by the known poses
  (`guided_geometric_verification` with the posed reconstruction) and two-view tracks kept
  (`ignore_two_view_tracks` off) as ours keeps them.

Per method: points, mean track length, mean reprojection error (px), seconds (one thread:
OMP_NUM_THREADS=1, OpenCV and COLMAP on one thread), and accuracy without the method's own
numbers: on a synthetic capture, the distance of each point to the ground-truth surface (the
smallest |z - depth| over the views it projects into, gt/depth), as a median and the share
within 1 % of the cameras' distance; on a real capture (no ground truth), the same against the
held-out views' depth from our plane sweep over all views given no sparse points
(`--stereo-reference`, `core.rig.depth`: depth that passed the cross-view consistency check), the
median distance from each method's points to the other's nearest point, and the colour of each
point against the held-out views it lands in (median |difference|, 0..1).

    PYTHONPATH=$PWD:/tmp/pycolmap-site OMP_NUM_THREADS=1 \\
        python benchmarks/triangulators.py CAPTURE [--downscale 4] [--frame F] \\
        [--stereo-reference] [--out FILE] [--work DIR]

CAPTURE: a capture folder (capture.json) or any importable source (transforms.json, ...).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.data import import_capture, load_capture  # noqa: E402
from core.data.capture import Camera  # noqa: E402
from core.data.points import PointCloud  # noqa: E402
from core.triangulation import (TriangulationConfig, camera_pairs, in_visual_hull,  # noqa: E402
                                pixel_indices, triangulate_views)


def _u8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image[..., :3], 0, 1) * 255 + 0.5).astype(np.uint8)


def colmap_triangulate(cameras: list[Camera], images: list[np.ndarray],
                       masks: list[np.ndarray | None], work: Path, matches: str = "colmap",
                       config: TriangulationConfig = TriangulationConfig()) -> tuple[
                           PointCloud, dict]:
    """Points from COLMAP's triangulator with the cameras' poses and intrinsics fixed.
    `matches`: `colmap` (COLMAP SIFT, matching, RANSAC verification) or `guided` (the same
    matches verified by the known poses, two-view tracks kept)."""
    import pycolmap

    pycolmap.logging.minloglevel = 2  # warnings and errors only
    seconds: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        seconds[name] = seconds.get(name, 0.0) + now - clock
        clock = now

    work.mkdir(parents=True, exist_ok=True)
    (work / "images").mkdir()
    (work / "masks").mkdir()
    names = [f"{i:04d}.png" for i in range(len(cameras))]
    for name, img, mask in zip(names, images, masks):
        cv2.imwrite(str(work / "images" / name), cv2.cvtColor(_u8(img), cv2.COLOR_RGB2BGR))
        if mask is not None:  # COLMAP: no features where the mask <name>.png is zero
            cv2.imwrite(str(work / "masks" / f"{name}.png"),
                        ((mask[..., 0] > 0.5) * 255).astype(np.uint8))
    lap("write")
    db = work / "database.db"
    reader = pycolmap.ImageReaderOptions(camera_model="PINHOLE")
    if any(m is not None for m in masks):
        reader.mask_path = work / "masks"
    pairs = camera_pairs(cameras, config.neighbours, config.max_axis_angle)
    index = {n: i for i, n in enumerate(names)}
    extraction = pycolmap.FeatureExtractionOptions(num_threads=1)
    extraction.sift.max_num_features = config.max_features
    pycolmap.extract_features(db, work / "images", image_names=names,
                              camera_mode=pycolmap.CameraMode.PER_IMAGE,
                              reader_options=reader, extraction_options=extraction,
                              device=pycolmap.Device.cpu)
    lap("features")
    with pycolmap.Database.open(db) as d:  # our intrinsics for the ones it guessed
        ids = {}
        for image in d.read_all_images():
            cam, K = d.read_camera(image.camera_id), cameras[index[image.name]].K
            cam.params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
            d.update_camera(cam)
            ids[index[image.name]] = image.image_id
    (work / "pairs.txt").write_text("".join(f"{names[a]} {names[b]}\n" for a, b in pairs))
    matching = pycolmap.FeatureMatchingOptions(num_threads=1)
    matching.sift.max_ratio = config.ratio
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.num_threads = 1
    pycolmap.match_image_pairs(
        db, matching_options=matching, verification_options=verification,
        pairing_options=pycolmap.ImportedPairingOptions(match_list_path=work / "pairs.txt"),
        device=pycolmap.Device.cpu)
    lap("matching")
    rec = pycolmap.Reconstruction()
    with pycolmap.Database.open(db) as d:
        stats = {"features": d.num_keypoints(), "matches": d.num_matches()}
        for cam in d.read_all_cameras():
            rec.add_camera(cam)
        for rig in d.read_all_rigs():
            rec.add_rig(rig)
        db_images = {im.image_id: im for im in d.read_all_images()}
        frames = d.read_all_frames()
        for frame in frames:  # one camera per frame (PER_IMAGE): the frame's pose is its own
            cam = cameras[index[db_images[frame.image_ids[0].id].name]]
            frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t)
            rec.add_frame(frame)
        for image in db_images.values():
            rec.add_image(image)
        for frame in frames:
            rec.register_frame(frame.frame_id)
    options = pycolmap.IncrementalPipelineOptions(num_threads=1)
    if matches == "guided":  # two-view tracks kept, as ours keeps them
        options.triangulation.ignore_two_view_tracks = False
        options.min_num_matches = 1  # the matches' inliers from the known poses, not from RANSAC
        verification.min_num_inliers = 1
        pycolmap.guided_geometric_verification(rec, db, two_view_geometry_options=verification,
                                               num_threads=1)
        lap("matching")
    with pycolmap.Database.open(db) as d:
        stats["inlier_matches"] = d.num_inlier_matches()
    (work / "sparse").mkdir()
    out = pycolmap.triangulate_points(rec, db, work / "images", work / "sparse",
                                      clear_points=True, options=options)
    lap("triangulation")
    ids = sorted(out.points3D.keys())
    pts = np.array([out.points3D[i].xyz for i in ids]).reshape(-1, 3)
    cols = np.array([out.points3D[i].color for i in ids]).reshape(-1, 3) / 255.0
    lengths = np.array([out.points3D[i].track.length() for i in ids])
    errors = np.array([out.points3D[i].error for i in ids])  # mean over its track
    hull = in_visual_hull(pts, cameras, masks) if len(pts) else np.zeros(0, bool)
    cloud = PointCloud(pts[hull], cols[hull].astype(np.float32))
    obs = int(lengths[hull].sum())
    stats.update(points=len(cloud), observations=obs,
                 reprojection=float((errors[hull] * lengths[hull]).sum() / max(obs, 1)),
                 points_before_hull=len(pts), stage_seconds=seconds)
    return cloud, stats


def surface_error(points: np.ndarray, cameras: list[Camera], depths: list[np.ndarray]
                  ) -> np.ndarray:
    """(N,) each point's smallest |z - depth| over the views it projects onto the surface in
    (inf when none)."""
    best = np.full(len(points), np.inf)
    for cam, depth in zip(cameras, depths):
        uv, z = cam.project(points)
        u, v, inside = pixel_indices(uv, cam.width, cam.height, z)
        d = depth[v, u]
        ok = inside & (d > 0)
        best[ok] = np.minimum(best[ok], np.abs(z[ok] - d[ok]))
    return best


def nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a),) distance from each point of a to the nearest of b."""
    from scipy.spatial import cKDTree

    if not len(a) or not len(b):
        return np.full(len(a), np.inf)
    return cKDTree(b).query(a)[0]


def held_out_colour(cloud: PointCloud, cameras: list[Camera], images: list[np.ndarray]
                    ) -> float:
    """Median |point colour - held-out pixel| over the held-out views each point lands in."""
    diffs = []
    for cam, img in zip(cameras, images):
        uv, z = cam.project(cloud.points)
        u, v, inside = pixel_indices(uv, cam.width, cam.height, z)
        diffs.append(np.abs(img[v, u, :3] - cloud.colors)[inside].mean(axis=1))
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    return float(np.median(d)) if len(d) else float("nan")


def views_of(capture, frame: str, downscale: float, which: str):
    """(cameras, images, masks) of one frame's training or held-out ('scored') views at the
    run's resolution, as the trainer serves them (undistorted, downscaled)."""
    from core.config.views import select_views
    from core.data import CaptureDataset

    views = select_views(capture, downscale=downscale)
    cams = views.split.training if which == "training" else views.split.heldout
    if not cams:
        return [], [], []
    ds = CaptureDataset(capture, frames=[frame], cameras=list(cams), downscale=downscale,
                        matte=views.matte)
    samples = [ds[i] for i in range(len(ds))]
    return ([s.camera for s in samples], [s.image.numpy().astype(np.float64) for s in samples],
            [None if s.mask is None else s.mask.numpy() for s in samples])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--frame", default=None)
    ap.add_argument("--out", type=Path, default=None, help="JSON report here")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: temp)")
    ap.add_argument("--stereo-reference", action="store_true",
                    help="no ground truth: the plane sweep's fused depth of the held-out views "
                         "(all views, no sparse points) is the surface")
    ap.add_argument("--stereo-cache", type=Path, default=None,
                    help="an .npz that keeps the stereo reference between runs")
    ap.add_argument("--methods", nargs="+", default=["ours", "colmap", "colmap-guided"])
    args = ap.parse_args()
    cv2.setNumThreads(1)
    work = args.work or Path(tempfile.mkdtemp(prefix="triangulators-"))
    if (args.capture / "capture.json").is_file():
        capture = load_capture(args.capture)
    else:
        capture = import_capture(args.capture, work / "capture")
    frame = args.frame or capture.frames[0]
    cams, imgs, masks = views_of(capture, frame, args.downscale, "training")
    held = views_of(capture, frame, args.downscale, "scored")
    gt = capture.root / "gt" / "depth" / frame
    depths = None
    if gt.is_dir():  # ground truth at the capture's resolution, served cameras at theirs
        depths = [cv2.resize(np.load(gt / f"{c.id}.npy"), (c.width, c.height),
                             interpolation=cv2.INTER_NEAREST) for c in cams]
    ref_cams = cams
    if depths is None and args.stereo_reference and held[0]:
        from core.rig.depth import rig_depth

        t = time.perf_counter()
        cache = args.stereo_cache
        if cache is not None and cache.is_file():
            saved = np.load(cache)
            depths = [saved[f"d{i}"] for i in range(len(held[0]))]
            ref_cams = [c.scaled(d.shape[1], d.shape[0]) for c, d in zip(held[0], depths)]
        else:
            fused = rig_depth(cams + held[0], imgs + held[1], masks + held[2])
            ref_cams, depths = fused.cameras[len(cams):], fused.depths[len(cams):]
            if cache is not None:
                np.savez(cache, **{f"d{i}": d for i, d in enumerate(depths)})
        print(f"stereo reference: {len(depths)} held-out depth maps "
              f"{ref_cams[0].width}x{ref_cams[0].height}, "
              f"{np.mean([np.mean(d > 0) for d in depths]):.0%} of their pixels, "
              f"{time.perf_counter() - t:.0f} s", flush=True)
    centers = np.stack([c.center for c in cams])
    scale = float(np.median(np.linalg.norm(centers - centers.mean(axis=0), axis=1)))
    print(f"{args.capture} frame {frame} at 1/{args.downscale:g}: {len(cams)} training views "
          f"{cams[0].width}x{cams[0].height}, {len(held[0])} held out", flush=True)
    clouds, rows = {}, {}
    for method in args.methods:
        t = time.perf_counter()
        if method == "ours":
            cloud, st = triangulate_views(cams, imgs, masks)
            stats = {"features": st.features, "matches": st.matches, "points": st.points,
                     "observations": st.observations, "reprojection": st.reprojection}
        else:
            cloud, stats = colmap_triangulate(cams, imgs, masks, work / method,
                                              matches=method.partition("-")[2] or "colmap")
        stats["seconds"] = time.perf_counter() - t
        stats["track_length"] = stats["observations"] / max(stats["points"], 1)
        if depths is not None and len(cloud):
            err = surface_error(cloud.points, ref_cams, depths)
            stats["surface_median"] = float(np.median(err))
            stats["surface_within_1pct"] = float(np.mean(err < 0.01 * scale))
            stats["surface_points"] = int(np.isfinite(err).sum())
        if held[0] and len(cloud):
            stats["held_out_colour"] = held_out_colour(cloud, held[0], held[1])
        clouds[method], rows[method] = cloud, stats
        print(method, json.dumps(stats), flush=True)
    for a in clouds:
        for b in clouds:
            if a != b:
                d = nearest(clouds[a].points, clouds[b].points)
                rows[a][f"to_{b}_median"] = float(np.median(d)) if len(d) else float("nan")
    report = {"capture": str(args.capture), "frame": frame, "downscale": args.downscale,
              "views": len(cams), "size": [cams[0].width, cams[0].height], "scale": scale,
              "methods": rows}
    print(table(report))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=1))
    return 0


def table(report: dict) -> str:
    lines = [f"{report['capture']} ({report['views']} views, {report['size'][0]}x"
             f"{report['size'][1]}, camera distance {report['scale']:.3f})",
             "| method | points | track length | reprojection (px) | seconds | surface median "
             "| within 1 % (points) | held-out colour | to the other (median) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in report["methods"].items():
        other = ", ".join(f"{k[3:-7]} {v:.4f}" for k, v in r.items()
                          if k.startswith("to_") and k.endswith("_median"))
        surf = f"{r['surface_median']:.4f}" if "surface_median" in r else "-"
        within = (f"{100 * r['surface_within_1pct']:.0f} % "
                  f"({round(r['surface_within_1pct'] * r['points'])})"
                  if "surface_within_1pct" in r else "-")
        colour = f"{r['held_out_colour']:.3f}" if "held_out_colour" in r else "-"
        lines.append(f"| {name} | {r['points']} | {r['track_length']:.2f} | "
                     f"{r['reprojection']:.3f} | {r['seconds']:.2f} | {surf} | {within} | "
                     f"{colour} | {other} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
