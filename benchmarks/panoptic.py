"""Real volumetric video (issue 29): the CMU Panoptic basketball sequence as Dynamic 3D Gaussians
prepared it (31 cameras, 150 frames, 640x360), end to end, scored by that paper's protocol.

Steps, each written under OUT as it ends (a run cut short keeps what it measured):

1. `dgs capture import` of SRC (format `panoptic`, hard links) into OUT/source, and a canonical
   capture of the chosen frames (`--frames`, hard links) in OUT/capture;
2. the reconstruction through `dgs reconstruct` (in this process: per frame its seconds, key
   and tracked frames apart, and the peak GPU memory) into OUT/run, resumed when it exists;
   with `--serve N` also through a real `dgs serve --workers N` (the job as parts, one per
   group of pictures) into OUT/service-N/run;
3. `dgs eval`: PSNR and SSIM of the whole image on the dataset's test cameras (0, 10, 15, 30:
   capture.json test_cameras, the run's `split` auto), every frame; RUN/contact_sheet.png;
4. the subject (the Gaussians inside the masks' hull: the players and the ball) exported as the
   relightable stream, its bytes a frame and its decoded renders against the uncompressed
   subject's on the test cameras; the subject's meshes per frame (`mesh.subject`);
5. the relit MP4 of the first test camera over the frames under an HDRI (`--hdri`);
6. with `--plain`, the honest baseline: a plain 3DGS (`train.method` 3dgs) trained on every
   frame independently (groups of 1) at the same steps a frame, cap and seeds, into OUT/plain,
   scored the same way.

Each key frame's seeds (dense points fused from the views' stereo depth where the capture has
no point cloud, `core.rig`) and normal priors are timed apart from its training: the table
gives their share of the key frame.

The schedule: `--preset`'s plan scaled to `--steps` a key frame (`Schedule.scaled`), groups of
`--gop` frames. The CPU twin (docs/benchmarks.md): `--frames 0:10 --downscale 2` with the
steps that finish in about 30 minutes on two cores; the GPU run: every frame at 640x360.

    python benchmarks/panoptic.py [SRC] --out DIR --pack --frames 0:50   (a slice to carry)
    python benchmarks/panoptic.py [SRC] --out DIR [--frames 0:10] [--downscale 2]
        [--preset fast] [--steps N] [--gop 10] [--max-gaussians N] [--mesh-voxels 256]
        [--serve N] [--hdri EXR] [--plain]
        [--device auto] [--threads N]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SRC = ROOT.parent / "shared" / "data" / "panoptic_basketball"
HDRI = ROOT.parent / "shared" / "data" / "hdri"

# Published on this sequence by the protocol above (PSNR dB, SSIM, LPIPS; None: not given).
PUBLISHED = (
    ("Dynamic 3D Gaussians (Luiten et al. 2024)", 28.22, 0.91, 0.18),
    ("Dynamic 3D Gaussians, re-run in later papers", "27.81-28.54", "0.893-0.903", None),
    ("S4D", 27.72, 0.920, 0.142),
    ("HiCoM", 27.29, None, None),
    ("MAGS", 29.60, 0.918, 0.164),
)


def pack(src: Path, dst: Path, frames: str | None) -> int:
    """A copy of the source layout holding only the chosen frames (what a GPU machine that
    takes at most 64 MiB is sent: `--pack DIR` here, then the script there on DIR); returns
    its bytes."""
    import shutil

    from core.config import parse_frames

    meta = json.loads((src / "train_meta.json").read_text())
    names = [fn.rsplit("/", 1)[-1].rsplit(".", 1)[0] for fn in (f[0] for f in meta["fn"])]
    keep = [names.index(n) for n in parse_frames(frames, names)]
    total = 0
    for split in ("train_meta.json", "test_meta.json"):
        if not (src / split).is_file():
            continue
        meta = json.loads((src / split).read_text())
        for key in ("k", "w2c", "fn", "cam_id"):
            meta[key] = [meta[key][t] for t in keep]
        dst.mkdir(parents=True, exist_ok=True)
        (dst / split).write_text(json.dumps(meta))
        for fns in meta["fn"]:
            for fn in fns:
                stem = fn.rsplit(".", 1)[0]
                for kind, rel in (("ims", fn), ("seg", f"{stem}.png")):
                    if (src / kind / rel).is_file():
                        (dst / kind / rel).parent.mkdir(parents=True, exist_ok=True)
                        shutil.copyfile(src / kind / rel, dst / kind / rel)
                        total += (dst / kind / rel).stat().st_size
    return total


def prepare(src: Path, out: Path, frames: str | None) -> Path:
    """OUT/capture: the chosen frames of SRC in the canonical layout (hard links)."""
    from core.config import parse_frames
    from core.data import import_capture, load_capture, save_capture

    source = out / "source"
    if not (source / "capture.json").is_file():
        import_capture(src, source, "panoptic", link=True)
    full = load_capture(source)
    chosen = parse_frames(frames, full.frames)
    capture = out / "capture"
    if (capture / "capture.json").is_file() and list(load_capture(capture).frames) == chosen:
        return capture
    for frame in chosen:
        for kind in ("images", "masks"):
            folder = source / kind / frame
            if not folder.is_dir():
                continue
            (capture / kind / frame).mkdir(parents=True, exist_ok=True)
            for f in folder.iterdir():
                dst = capture / kind / frame / f.name
                if not dst.exists():
                    os.link(f, dst)
    full.frames = tuple(chosen)
    save_capture(full, capture)
    return capture


def overrides(args) -> dict:
    from dataclasses import asdict

    from core.config import train_config

    s = train_config(args.preset).schedule
    if args.steps:
        s = s.scaled(args.steps)
    train = {"schedule": asdict(s), "rates": {"means_decay_steps": s.iterations},
             "device": args.device}
    if args.max_gaussians:
        train["densify"] = {"max_gaussians": args.max_gaussians}
    return {"downscale": args.downscale, "gop": args.gop, "train": train,
            "mesh": {"enabled": args.mesh_voxels > 0, "subject": True,
                     "resolution": max(args.mesh_voxels, 16)}}


def plain_overrides(args) -> dict:
    """The per-frame plain 3DGS: the run's settings with `train.method` 3dgs (its defaults
    under them) and every frame a key frame of its own, at the run's steps a key frame."""
    over = overrides(args)
    over["train"]["method"] = "3dgs"
    over["gop"] = 1
    over["mesh"] = {"enabled": False}
    return over


def reconstruct_here(capture: Path, run: Path, args, over: dict | None = None) -> dict:
    """`dgs reconstruct` in this process; per frame the peak GPU memory (bytes, CUDA only)."""
    import torch

    from core.pipeline import reconstruct

    peaks: dict[str, int] = {}
    cuda = torch.cuda.is_available() and args.device != "cpu"

    def on_progress(event) -> None:
        if not cuda:
            return
        if event.kind == "frame_start":
            torch.cuda.reset_peak_memory_stats()
        elif event.kind == "frame_done":
            peaks[event.frame] = int(torch.cuda.max_memory_allocated())

    start = time.perf_counter()
    reconstruct(capture, run, preset=args.preset, overrides=over or overrides(args),
                resume=True, progress=True, on_progress=on_progress)
    old = json.loads((run / "peaks.json").read_text()) if (run / "peaks.json").is_file() else {}
    peaks = {**old, **peaks}
    (run / "peaks.json").write_text(json.dumps(peaks))
    return {"wall": time.perf_counter() - start, "peaks": peaks}


def reconstruct_served(capture: Path, out: Path, args) -> dict:
    """The same job through a real `dgs serve --workers N` (as parts)."""
    from benchmarks.scaleout import part_times, service

    params = {"preset": args.preset, "config": overrides(args)}
    result = service(capture, out, params, args.serve)
    spans, assembly = part_times(result["job"])
    return {"wall": result["wall"], "run": str(result["run"]), "parts": spans,
            "assembly": assembly}


def frame_rows(run: Path, ev: dict, peaks: dict) -> list[dict]:
    metrics = json.loads((run / "metrics.json").read_text())["frames"]
    scores = {f["frame"]: f for f in ev["per_frame"]}
    rows = []
    for frame, m in metrics.items():
        mesh = m.get("mesh") or {}
        rows.append({"frame": frame, "kind": "key" if m["stages"].startswith("static")
                     else "tracked", "seconds": m["seconds"], "gaussians": m["gaussians"],
                     "ao_bake_seconds": m.get("ao_bake_seconds"),
                     "seed_seconds": m.get("seed_seconds"),
                     "prior_seconds": (m.get("rig_seconds") or {}).get("priors"),
                     "mesh_seconds": (mesh.get("seconds") or {}).get("total"),
                     "peak_gb": peaks.get(frame, 0) / 1e9 or None,
                     "psnr": scores[frame]["psnr_full"], "ssim": scores[frame]["ssim"]})
    return rows


def plain_baseline(capture: Path, run: Path, args) -> dict:
    """The per-frame plain 3DGS (`plain_overrides`) trained and scored: PSNR, SSIM (and LPIPS
    where the evaluation gives it) over the same test cameras and frames, its mean seconds
    and Gaussians a frame."""
    from core.evaluation import evaluate_run

    reconstruct_here(capture, run, args, plain_overrides(args))
    ev = evaluate_run(run)
    frames = json.loads((run / "metrics.json").read_text())["frames"].values()
    return {**{k: ev.get(k) for k in ("psnr_full", "ssim", "lpips")},
            "seconds": sum(f["seconds"] for f in frames) / len(frames),
            "gaussians": sum(f["gaussians"] for f in frames) / len(frames),
            "per_frame": [{"frame": f["frame"], "psnr": f["psnr_full"], "ssim": f["ssim"]}
                          for f in ev["per_frame"]]}


def subject_stream(run: Path, out: Path) -> dict:
    from benchmarks.stream import score_run
    from core.export.codec import StreamConfig

    r = score_run(run, out, StreamConfig(), subject=True)
    record = json.loads((out / "export.json").read_text())
    return {"bytes_per_frame": r["stream"]["bytes"], "psnr_min": r["stream"]["psnr_min"],
            "psnr_mean": r["stream"]["psnr_mean"], "gaussians": r["gaussians"],
            "share": record["subject"]["share"], "ply_bytes": r["ply_bytes"]}


def relit_video(run: Path, out: Path, hdri: Path, camera: str) -> str:
    from core.relight.run import relight_run

    record = relight_run(run, out, envmap=hdri, cameras=camera, fps=30.0)
    return str(out / record["videos"][0]) if record["videos"] else ""


def sheet(capture: Path, run: Path, relit: Path, camera: str, out: Path) -> Path:
    """OUT/sheet.png: the test camera at the first, middle and last frame, as `dgs eval`'s
    contact sheet draws a view (capture, render, normal, AO), relit under the HDRI beside it
    (the relit video's frames)."""
    import numpy as np
    from PIL import Image

    from core.data import load_capture
    from core.relight.sheet import contact_sheet

    frames = sorted(p.name for p in (run / "renders").iterdir() if p.is_dir())
    views = [(f, camera) for f in dict.fromkeys([frames[0], frames[len(frames) // 2],
                                                  frames[-1]])]
    pictures = {(f, camera): {"relit (HDRI)": np.asarray(Image.open(path).convert("RGB"))
                              / 255.0}
                for f, _ in views if (path := relit / f / f"{camera}.png").is_file()}
    matte = load_capture(capture).masks == "matte"  # Panoptic's mark the players: "subject"
    return contact_sheet(capture, run, views, pictures, out / "sheet.png", scale=1, matte=matte)


def _fmt(v, spec: str) -> str:
    return "-" if v is None else (v if isinstance(v, str) else format(v, spec))


def report(rows: list[dict], ev: dict, stream: dict | None, args,
           plain: dict | None = None) -> None:
    import numpy as np

    key = [r for r in rows if r["kind"] == "key"]
    tracked = [r for r in rows if r["kind"] == "tracked"]
    print(f"\nPanoptic basketball, frames {args.frames or 'all'} ({len(rows)}), 1/"
          f"{args.downscale:g}, preset {args.preset}{f' at {args.steps} steps' if args.steps else ''}"
          f", groups of {args.gop}; test cameras {', '.join(ev['split']['heldout'])}\n")
    print("| frame | kind | s | Gaussians | peak GB | PSNR | SSIM |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['frame']} | {r['kind']} | {r['seconds']:.1f} | {r['gaussians']} | "
              f"{_fmt(r['peak_gb'], '.2f')} | {r['psnr']:.2f} | {r['ssim']:.4f} |")
    print("\n| | PSNR | SSIM | LPIPS |\n|---|---|---|---|")
    for name, p, s, lp in PUBLISHED:
        print(f"| {name} (published) | {_fmt(p, '.2f')} | {_fmt(s, '.3f')} | {_fmt(lp, '.2f')} |")
    print(f"| ours, relightable | {ev['psnr_full']:.2f} | {ev['ssim']:.4f} | "
          f"{_fmt(ev.get('lpips'), '.3f')} |")
    if plain:
        print(f"| plain 3DGS, every frame independently | {plain['psnr_full']:.2f} | "
              f"{plain['ssim']:.4f} | {_fmt(plain.get('lpips'), '.3f')} |")
    mean = (lambda xs: float(np.mean(xs)) if xs else None)
    bake = [r["ao_bake_seconds"] / r["seconds"] for r in key if r["ao_bake_seconds"]]
    meshes = [r["mesh_seconds"] for r in rows if r["mesh_seconds"]]
    seeds = [r["seed_seconds"] / r["seconds"] for r in key if r.get("seed_seconds")]
    priors = [r["prior_seconds"] / r["seconds"] for r in key if r.get("prior_seconds")]
    print(f"\nkey frame {_fmt(mean([r['seconds'] for r in key]), '.1f')} s (AO bake "
          f"{_fmt(mean(bake), '.1%')}, seeds {_fmt(mean(seeds), '.1%')}, priors "
          f"{_fmt(mean(priors), '.1%')}), tracked frame "
          f"{_fmt(mean([r['seconds'] for r in tracked]), '.1f')} s"
          f", subject mesh {_fmt(mean(meshes), '.2f')} s a frame")
    if plain:
        print(f"plain 3DGS: {_fmt(plain['seconds'], '.1f')} s a frame, "
              f"{_fmt(plain['gaussians'], '.0f')} Gaussians a frame")
    if stream:
        print(f"subject stream: {stream['bytes_per_frame'] / 1e6:.3f} MB a frame "
              f"({stream['gaussians']:.0f} Gaussians, {stream['share']:.1%} of the scene's), "
              f"{stream['psnr_min']:.1f} dB worst / {stream['psnr_mean']:.1f} dB mean against "
              "the uncompressed subject")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path, nargs="?", default=SRC)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--pack", action="store_true",
                    help="only copy the chosen frames of SRC, in its own layout, into OUT (to "
                         "carry a slice to a GPU machine)")
    ap.add_argument("--frames", default=None, help="slice of the 150 frames (default all)")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--steps", type=int, default=None, help="a key frame's steps")
    ap.add_argument("--gop", type=int, default=10)
    ap.add_argument("--max-gaussians", type=int, default=None,
                    help="densification's cap (the CPU twin's budget; default: none)")
    ap.add_argument("--mesh-voxels", type=int, default=256, help="0: no meshes")
    ap.add_argument("--serve", type=int, default=0, metavar="N",
                    help="also run through dgs serve --workers N")
    ap.add_argument("--hdri", type=Path, default=HDRI / "studio.exr")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--plain", action="store_true",
                    help="also a plain 3DGS on every frame independently (OUT/plain)")
    args = ap.parse_args(argv)
    if not (args.src / "train_meta.json").is_file():
        print(f"no Panoptic capture at {args.src} (see ../shared/data/README.md)")
        return 2
    if args.pack:
        size = pack(args.src, args.out, args.frames)
        print(f"packed frames {args.frames or 'all'} into {args.out}: {size / 2**20:.1f} MiB")
        return 0
    import torch

    from core.evaluation import evaluate_run

    if args.threads:
        torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    result: dict = {"args": {k: str(v) for k, v in vars(args).items()}}

    def save() -> None:
        (args.out / "result.json").write_text(json.dumps(result, indent=2))

    capture = prepare(args.src, args.out, args.frames)
    run = args.out / "run"
    result["reconstruct"] = reconstruct_here(capture, run, args)
    save()
    ev = evaluate_run(run)
    result["rows"] = frame_rows(run, ev, result["reconstruct"]["peaks"])
    result["eval"] = {k: ev[k] for k in ("psnr_full", "ssim", "lpips", "split")}
    save()
    result["subject_stream"] = subject_stream(run, args.out / "subject")
    save()
    if args.hdri.is_file():
        test = ev["split"]["heldout"][0]
        result["relit_video"] = relit_video(run, args.out / "relit", args.hdri, test)
        result["sheet"] = str(sheet(capture, run, args.out / "relit", test, args.out))
        save()
    if args.serve:
        result["service"] = reconstruct_served(capture, args.out, args)
        save()
    if args.plain:
        result["plain"] = plain_baseline(capture, args.out / "plain", args)
        save()
    report(result["rows"], ev, result["subject_stream"], args, result.get("plain"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
