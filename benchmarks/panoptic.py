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
   scored the same way; `--plain-only` runs it alone (the sequence's rows made elsewhere).

Each key frame's seeds (dense points fused from the views' stereo depth where the capture has
no point cloud, `core.rig`) and normal priors are timed apart: the table gives their share of
the key frame.

The schedule: `--preset`'s plan scaled to `--steps` a key frame (`Schedule.scaled`), groups of
`--gop` frames. The CPU twin (docs/benchmarks.md): `--frames 0:10 --downscale 2` with the
steps that finish in about 30 minutes on two cores; the GPU run: every frame at 640x360.

A run with a time limit (`--deadline`, seconds from the start) starts a frame only when its
predicted seconds (the mean of its kind so far), the extras' reserve and the served job's
still fit; it then packs what the next call continues from (`core.pipeline.carry`: the records,
the last frame's Gaussians when it stopped inside a group) into `--pack-to`. `--resume-from`
lays such a pack out as OUT/run and continues it; the earlier call's rows come from its r.tgz.

    python benchmarks/panoptic.py [SRC] --out DIR --pack --frames 0:50   (a slice to carry)
    python benchmarks/panoptic.py [SRC] --out DIR [--frames 0:10] [--downscale 2]
        [--preset fast] [--steps N] [--gop 10] [--max-gaussians N] [--mesh-voxels 256]
        [--serve N] [--serve-frames 0:12] [--hdri EXR] [--plain | --plain-only]
        [--deadline S] [--reserve S] [--pack-to DIR] [--resume-from DIR]
        [--device auto] [--threads N] [--set KEY=VALUE ...]
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
    over = {"downscale": args.downscale, "gop": args.gop, "train": train,
            "mesh": {"enabled": args.mesh_voxels > 0, "subject": True,
                     "resolution": max(args.mesh_voxels, 16)}}
    for setting in args.set:
        lay_setting(over, setting)
    return over


def lay_setting(over: dict, setting: str) -> None:
    """`--set KEY=VALUE` laid on the overrides `over`: KEY a dotted path of RUN/config.json's
    `config` (train.near), VALUE JSON (a bare word: a string); the run's validation checks
    it."""
    key, sep, text = setting.partition("=")
    if not sep or not key:
        raise SystemExit(f"--set: expected KEY=VALUE, got {setting!r}")
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = text
    *path, last = key.split(".")
    node = over
    for name in path:
        node = node.setdefault(name, {})
        if not isinstance(node, dict):
            raise SystemExit(f"--set: {key} goes inside {name}, which is not a section")
    node[last] = value


def plain_overrides(args) -> dict:
    """The per-frame plain 3DGS: the run's settings with `train.method` 3dgs (its defaults
    under them) and every frame a key frame of its own, at the run's steps a key frame."""
    over = overrides(args)
    over["train"]["method"] = "3dgs"
    over["gop"] = 1
    over["mesh"] = {"enabled": False}
    return over


def reconstruct_here(capture: Path, run: Path, args, budget, over: dict | None = None) -> dict:
    """`dgs reconstruct` in this process (`over`: other overrides than the run's); per frame
    the peak GPU memory (bytes, CUDA only); stopped by `budget` (the frame it stopped in, if
    any)."""
    import torch

    from core.pipeline import Stopped, reconstruct

    peaks: dict[str, int] = {}
    cuda = torch.cuda.is_available() and args.device != "cpu"

    def on_progress(event) -> None:
        budget.on_progress(event)
        if not cuda:
            return
        if event.kind == "frame_start":
            torch.cuda.reset_peak_memory_stats()
        elif event.kind == "frame_done":
            peaks[event.frame] = int(torch.cuda.max_memory_allocated())

    start, stopped = time.perf_counter(), None
    try:
        reconstruct(capture, run, preset=args.preset, overrides=over or overrides(args),
                    resume=True, progress=True, on_progress=on_progress,
                    should_stop=budget.should_stop)
    except Stopped as exc:
        stopped = exc.frame
    old = json.loads((run / "peaks.json").read_text()) if (run / "peaks.json").is_file() else {}
    peaks = {**old, **peaks}
    (run / "peaks.json").write_text(json.dumps(peaks))
    return {"wall": time.perf_counter() - start, "peaks": peaks, "stopped_in": stopped,
            "seconds": budget.seconds}


def reconstruct_served(capture: Path, out: Path, args) -> dict:
    """The same job through a real `dgs serve --workers N` (as parts)."""
    from benchmarks.scaleout import part_times, service

    params = {"preset": args.preset, "config": overrides(args), "frames": args.serve_frames}
    result = service(capture, out, params, args.serve)
    spans, assembly = part_times(result["job"])
    return {"wall": result["wall"], "run": str(result["run"]), "parts": spans,
            "assembly": assembly}


def frame_rows(run: Path, ev: dict, peaks: dict) -> list[dict]:
    """A row per frame `dgs eval` scored (the frames this call made)."""
    metrics = json.loads((run / "metrics.json").read_text())["frames"]
    rows = []
    for score in ev["per_frame"]:
        frame = score["frame"]
        m = metrics[frame]
        mesh = m.get("mesh") or {}
        rows.append({"frame": frame, "kind": "key" if m["stages"].startswith("static")
                     else "tracked", "seconds": m["seconds"], "gaussians": m["gaussians"],
                     "train_seconds": m.get("train_seconds"),
                     "extras_seconds": sum((m.get("extras_seconds") or {}).values()) or None,
                     "extras": m.get("extras_seconds"),
                     "ao_bake_seconds": m.get("ao_bake_seconds"),
                     "seed_seconds": m.get("seed_seconds"),
                     "prior_seconds": (m.get("rig_seconds") or {}).get("priors"),
                     "mesh_seconds": (mesh.get("seconds") or {}).get("total"),
                     "peak_gb": peaks.get(frame, 0) / 1e9 or None,
                     "psnr": score["psnr_full"], "ssim": score["ssim"],
                     "lpips": score.get("lpips")})
    return rows


def plain_baseline(capture: Path, run: Path, args) -> dict:
    """The per-frame plain 3DGS (`plain_overrides`) trained and scored: PSNR, SSIM and LPIPS
    over the same test cameras and frames, its mean seconds and Gaussians a frame."""
    from core.evaluation import evaluate_run
    from core.pipeline.carry import FrameBudget

    reconstruct_here(capture, run, args, FrameBudget(1, None, lambda b: 0.0),
                     plain_overrides(args))
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

    start = time.perf_counter()
    r = score_run(run, out, StreamConfig(), subject=True)
    record = json.loads((out / "export.json").read_text())
    return {"bytes_per_frame": r["stream"]["bytes"], "psnr_min": r["stream"]["psnr_min"],
            "psnr_mean": r["stream"]["psnr_mean"], "gaussians": r["gaussians"],
            "share": record["subject"]["share"], "ply_bytes": r["ply_bytes"],
            "seconds": time.perf_counter() - start}


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


def plain_lines(plain: dict) -> tuple[str, str]:
    """The per-frame plain 3DGS (`plain_baseline`): its row of the scores' table, and its
    seconds and Gaussians a frame."""
    return (f"| plain 3DGS, every frame independently | {plain['psnr_full']:.2f} | "
            f"{plain['ssim']:.4f} | {_fmt(plain.get('lpips'), '.3f')} |",
            f"plain 3DGS: {plain['seconds']:.1f} s and {plain['gaussians']:.0f} Gaussians a frame")


def report(rows: list[dict], ev: dict, stream: dict | None, args,
           plain: dict | None = None) -> None:
    """The table: per frame seconds (training, extras), peak GPU memory and the scores; then
    the published rows beside ours (the frames of every call), the means and the stream."""
    import numpy as np

    mean = (lambda xs: float(np.mean(xs)) if xs else None)
    key = [r for r in rows if r["kind"] == "key"]
    tracked = [r for r in rows if r["kind"] == "tracked"]
    print(f"\nPanoptic basketball, frames {args.frames or 'all'} ({len(rows)} scored), 1/"
          f"{args.downscale:g}, preset {args.preset}"
          f"{f' at {args.steps} steps' if args.steps else ''}, groups of {args.gop}; test "
          f"cameras {', '.join(ev['split']['heldout'])}, whole image\n")
    print("| frame | kind | train s | extras s | Gaussians | peak GB | PSNR | SSIM | LPIPS |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['frame']} | {r['kind']} | {_fmt(r.get('train_seconds'), '.1f')} | "
              f"{_fmt(r.get('extras_seconds'), '.2f')} | {r['gaussians']} | "
              f"{_fmt(r['peak_gb'], '.2f')} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
              f"{_fmt(r.get('lpips'), '.3f')} |")
    print("\n| | PSNR | SSIM | LPIPS |\n|---|---|---|---|")
    for name, p, s, lp in PUBLISHED:
        print(f"| {name} (published) | {_fmt(p, '.2f')} | {_fmt(s, '.3f')} | {_fmt(lp, '.2f')} |")
    print(f"| ours, relightable ({len(rows)} frames) | "
          f"{_fmt(mean([r['psnr'] for r in rows]), '.2f')} | "
          f"{_fmt(mean([r['ssim'] for r in rows]), '.4f')} | "
          f"{_fmt(mean([r['lpips'] for r in rows if r.get('lpips') is not None]), '.3f')} |")
    if plain:
        print(plain_lines(plain)[0])
    bake = [r["ao_bake_seconds"] / r["seconds"] for r in key if r["ao_bake_seconds"]]
    meshes = [r["mesh_seconds"] for r in rows if r["mesh_seconds"]]
    for name, group in (("key frame", key), ("tracked frame", tracked)):
        train = mean([r["train_seconds"] for r in group if r.get("train_seconds") is not None])
        extras = mean([r["extras_seconds"] for r in group if r.get("extras_seconds")])
        print(f"{name}: {_fmt(train, '.1f')} s training, {_fmt(extras, '.2f')} s extras "
              f"({len(group)} frames)")
    seeds = [r["seed_seconds"] / r["seconds"] for r in key if r.get("seed_seconds")]
    priors = [r["prior_seconds"] / r["seconds"] for r in key if r.get("prior_seconds")]
    print(f"AO bake {_fmt(mean(bake), '.1%')} of a key frame, seeds {_fmt(mean(seeds), '.1%')}"
          f", priors {_fmt(mean(priors), '.1%')}, subject mesh {_fmt(mean(meshes), '.2f')} s "
          "a frame")
    if plain:
        print(plain_lines(plain)[1])
    if stream:
        print(f"subject stream: {stream['bytes_per_frame'] / 1e6:.3f} MB a frame "
              f"({stream['gaussians']:.0f} Gaussians, {stream['share']:.1%} of the scene's), "
              f"{stream['psnr_min']:.1f} dB worst / {stream['psnr_mean']:.1f} dB mean against "
              f"the uncompressed subject, {stream.get('seconds', 0):.1f} s to export and score")


def report_service(service: dict) -> None:
    print(f"served (dgs serve, {len(service['parts'])} parts): {service['wall']:.1f} s, parts "
          + ", ".join(f"{s:.1f}" for s in service["parts"])
          + f" s, assembly {service['assembly']:.1f} s")


def arguments(argv: list[str] | None):
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
    ap.add_argument("--serve-frames", default="0:12",
                    help="the served job's frames (default: a group of 10 and 2 frames, two "
                         "parts at the fewest frames)")
    ap.add_argument("--hdri", type=Path, default=HDRI / "studio.exr")
    ap.add_argument("--deadline", type=float, default=None, metavar="S",
                    help="seconds from the start by which the script should end")
    ap.add_argument("--reserve", type=float, default=60.0, metavar="S",
                    help="seconds kept after the frames for scoring and the stream")
    ap.add_argument("--pack-to", type=Path, default=None,
                    help="where the resume files go (default OUT/resume)")
    ap.add_argument("--resume-from", type=Path, default=None,
                    help="a previous call's resume files (and its r.tgz or result.json)")
    ap.add_argument("--resume-mib", type=float, default=24.0,
                    help="largest resume pack (what the next call can carry beside its data)")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--plain", action="store_true",
                    help="also a plain 3DGS on every frame independently (OUT/plain)")
    ap.add_argument("--plain-only", action="store_true",
                    help="only the plain 3DGS on every frame (OUT/plain), no sequence")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a setting of RUN/config.json's config, dotted, VALUE JSON (e.g. "
                         "train.near=0.01; repeat for more)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    started = time.monotonic()
    args = arguments(argv)
    if not (args.src / "train_meta.json").is_file():
        print(f"no Panoptic capture at {args.src} (see ../shared/data/README.md)")
        return 2
    if args.pack:
        size = pack(args.src, args.out, args.frames)
        print(f"packed frames {args.frames or 'all'} into {args.out}: {size / 2**20:.1f} MiB")
        return 0
    import torch

    from core.evaluation import evaluate_run
    from benchmarks.panoptic_lend import resume_files, serve_reserve
    from core.pipeline.carry import FrameBudget, pack_resume
    from core.rundir import RunDir

    if args.threads:
        torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    result: dict = {"args": {k: str(v) for k, v in vars(args).items()}}

    def save() -> None:
        (args.out / "result.json").write_text(json.dumps(result, indent=2))

    capture = prepare(args.src, args.out, args.frames)
    if args.plain_only:
        result["plain"] = plain = plain_baseline(capture, args.out / "plain", args)
        save()
        row, timing = plain_lines(plain)
        print(f"{row}\nby frame: " + ", ".join(f"{f['psnr']:.2f}" for f in plain["per_frame"])
              + f"\n{timing}")
        return 0
    run = args.out / "run"
    earlier = resume_files(args, run)
    deadline = None if args.deadline is None else started + args.deadline
    budget = FrameBudget(args.gop, deadline,
                         lambda b: args.reserve + serve_reserve(args, b))
    result["reconstruct"] = reconstruct_here(capture, run, args, budget)
    save()
    result["resume"] = pack_resume(run, args.pack_to or args.out / "resume",
                                   budget=int(args.resume_mib * 2**20))
    save()
    made = set(RunDir(run).read_metrics().get("frames", {})) - RunDir(run).read_carried()
    if not made:
        print("no frame finished in this call: nothing to score (the resume files are written)")
        return 1
    ev = evaluate_run(run)
    done = {r["frame"] for r in frame_rows(run, ev, {})}
    result["rows"] = [r for r in earlier if r["frame"] not in done] + \
        frame_rows(run, ev, result["reconstruct"]["peaks"])
    result["eval"] = {k: ev[k] for k in ("psnr_full", "ssim", "lpips", "split")}
    save()
    report(result["rows"], ev, None, args)  # in the log now, whatever comes after
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
    if args.serve:
        report_service(result["service"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
