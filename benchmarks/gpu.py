"""GPU benchmark: our fused two-branch rasterizer (CUDA) against gsplat's `rasterization`.

At 1920x1080, for N in {100k, 1M, 3M} Gaussians (C=3 appearance channels, G=5 geometry
channels), on a scene shaped like a trained model (`surface_scene`: flat Gaussians about three
layers deep on a bumpy closed surface filling most of the frame, plus 5% floaters:
benchmarks/bench_scenes.py, as benchmarks/rasterizer.py uses), it measures forward+backward of

  (a) ours, both branches fused (geometry given, beta=0.5);
  (b) ours, appearance only (geometry=None, beta=0, opacity_g=opacity_c);
  (c) gsplat, one RGB pass (3 channels, opacity_c);
  (d) gsplat called twice: the appearance pass of (c) plus a geometry pass (5 channels +
      expected depth, render_mode "RGB+ED", opacity_g), forward and backward of both,

each as the median over --iters timed iterations after --warmup (torch.cuda.Event pairs, the
device synchronized before each iteration), with the forward alone (no_grad) beside it, and
the peak GPU memory of one forward+backward above what was allocated before it (the scene and
the loss weights). The loss touches every output: the sum of each output image times a fixed
random weight image. Equal settings: tile 16, eps2d 0.3, near 0.01, far 1e10, no
antialiasing (gsplat rasterize_mode "classic"), no background; gsplat otherwise at its
defaults (packed=True in 1.5.x, sh_degree=None: colors are (N, D) features). A cell that runs
out of memory reads "oom". Prints a Markdown table last (and writes it, with the raw numbers,
as JSON to --out after every cell, so a run cut short still leaves what it measured).
Targets, at 1M: (a) <= 1.25x (c) and (a) <= 0.65x (d).

`--check` instead compares our CUDA path with our CPU path on small scenes (default 20k
Gaussians at 320x240, float32 and float64, fused and appearance-only): max relative error
(max |cuda - cpu| / max |cpu|) of every output and every input's gradient, and, when gsplat
works, ours appearance-only against gsplat's RGB image (informational: gsplat clamps alpha at
0.999, ours at 0.99). `--check --bench` runs the check, then the benchmark.

gsplat: not needed for our numbers. If it cannot be imported, or its CUDA build fails, the
script still measures (a) and (b) and says why gsplat is missing. The repository's .whl/ holds
gsplat-1.5.3-py3-none-any.whl (pure Python: it JIT-compiles its CUDA sources on first use)
and packaging-*.whl (gsplat's backend imports `packaging`, which torch does not pull in); its
other requirements (torch, numpy, jaxtyping, rich, ninja) are expected to be installed. Install
with `python -m pip install --no-deps --no-index .whl/*.whl`; without that, the script extracts
the wheels into build/gpu_wheels/ and imports from there.

gsplat's JIT build (gsplat/cuda/_backend.py) runs on the first call of a CUDA op, not on
`import gsplat`, and takes minutes the first time. It goes through torch.utils.cpp_extension
into `$TORCH_EXTENSIONS_DIR/gsplat_cuda` when that is set, else
`${XDG_CACHE_HOME:-~/.cache}/torch_extensions/py312_cu130/gsplat_cuda` (py<ver>_cu<torch's
CUDA>); a finished build there (gsplat_cuda.so) is loaded without compiling, a folder without
it is deleted and rebuilt. Environment it reads: MAX_JOBS (ninja jobs; gsplat sets 10 when
unset), TORCH_CUDA_ARCH_LIST (torch: "9.0" compiles for the H100 only), FAST_COMPILE=1 (-O0,
do not benchmark that), NO_FAST_MATH=1 (drops -use_fast_math, on by default), VERBOSE=1,
USE_PRECOMPILED_HEADERS=1, and torch's CUDA_HOME for nvcc. This script sets MAX_JOBS to the
CPU count and TORCH_CUDA_ARCH_LIST to the device's capability (9.0 on an H100) when they are
unset, and builds our extension in a second process while gsplat builds, so the two builds
overlap. `--build-only` stops after the builds.

    python benchmarks/gpu.py [--sizes 100k,1M,3M] [--res 1920x1080] [--iters 20] [--warmup 3]
                             [--out bench_gpu.json] [--packed default|true|false]
                             [--no-gsplat] [--budget-s S] [--check [--bench]] [--build-only]

Without CUDA it prints that CUDA is needed and exits with status 2.
"""

from __future__ import annotations

import argparse
import gc
import glob
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
import zipfile
from dataclasses import fields
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_scenes import Scene, surface_scene, volume_scene  # noqa: E402  (those of rasterizer.py)

EPS2D = 0.3
NEAR = 0.01
FAR = 1e10
TILE = 16
DEVICE = "cuda"
BETA_FUSED = 0.5
C_APPEAR = 3
G_GEOM = 5
TARGET_RGB = 1.25     # (a) / (c) at 1M
TARGET_TWICE = 0.65   # (a) / (d) at 1M
CELLS = ("a", "b", "c", "d")
CELL_NAMES = {
    "a": "ours fused (both branches)",
    "b": "ours appearance only",
    "c": "gsplat RGB",
    "d": "gsplat twice (RGB + geometry/ED)",
}


# ----------------------------------------------------------------------------------- scenes


def on_device(scene: Scene, device=None, dtype=None, grad: bool | str = False) -> Scene:
    """A copy of `scene` on `device` in `dtype`; `grad`: its per-Gaussian tensors become leaves
    needing grad (every float tensor with grad == "all")."""
    import torch

    kw = {}
    for f in fields(scene):
        v = getattr(scene, f.name)
        if isinstance(v, torch.Tensor):
            v = v.detach().to(device=device, dtype=dtype).contiguous().clone()
            if grad and (grad == "all" or f.name not in ("viewmat", "K")):
                v.requires_grad_(True)
        kw[f.name] = v
    return Scene(**kw)


# ----------------------------------------------------------------------------------- builds


def _prepare_env() -> None:
    """Faster JIT builds where the caller set nothing: every core, the device's arch only."""
    import torch

    os.environ.setdefault("MAX_JOBS", str(os.cpu_count() or 8))
    if "TORCH_CUDA_ARCH_LIST" not in os.environ and torch.cuda.is_available():
        major, minor = torch.cuda.get_device_capability(0)
        os.environ["TORCH_CUDA_ARCH_LIST"] = f"{major}.{minor}"


def _extract_wheels() -> list[str]:
    """Make gsplat (and packaging) importable from .whl/ without pip: extract each wheel once
    into build/gpu_wheels/<wheel name>/ and put it on sys.path. Returns what it did."""
    done = []
    wanted = [("gsplat", "gsplat-*.whl"), ("packaging", "packaging-*.whl")]
    for module, pattern in wanted:
        try:
            __import__(module)
            continue
        except ImportError:
            pass
        wheels = sorted(glob.glob(str(ROOT / ".whl" / pattern)))
        if not wheels:
            continue
        wheel = Path(wheels[-1])
        target = ROOT / "build" / "gpu_wheels" / wheel.stem
        if not (target / ".extracted").is_file():
            target.mkdir(parents=True, exist_ok=True)
            with zipfile.ZipFile(wheel) as z:
                z.extractall(target)
            (target / ".extracted").write_text(wheel.name + "\n")
        sys.path.insert(0, str(target))
        done.append(f"{module} from {wheel.name} (extracted to {target})")
    return done


def _start_native_build() -> subprocess.Popen | None:
    """Build (or find built) our extension in a second process, so it overlaps gsplat's build;
    the main process then loads the cached library."""
    code = ("import sys; sys.path.insert(0, %r)\n"
            "import native._backend as b\n"
            "b.load()\n") % str(ROOT)
    try:
        log = tempfile.TemporaryFile(mode="w+")
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=log, stderr=subprocess.STDOUT)
        proc.log = log  # type: ignore[attr-defined]
        return proc
    except OSError:
        return None


def load_ours(proc: subprocess.Popen | None) -> tuple[bool, str, float]:
    """(usable on CUDA, note, build seconds). Tries a tiny CUDA call."""
    import torch

    t0 = time.perf_counter()
    build_log = ""
    if proc is not None:
        proc.wait()
        proc.log.seek(0)
        build_log = proc.log.read()
        proc.log.close()
        if proc.returncode != 0:
            tail = "\n".join(build_log.strip().splitlines()[-25:])
            return False, f"our extension failed to build (exit {proc.returncode}):\n{tail}", \
                time.perf_counter() - t0
    try:
        import native
        import native._backend

        native._backend.load()
    except Exception as exc:  # noqa: BLE001
        return False, f"our extension failed to build/load: {_short(exc)}\n{build_log[-2000:]}", \
            time.perf_counter() - t0
    secs = time.perf_counter() - t0
    has_cuda = getattr(native._backend, "has_cuda", None)
    if DEVICE == "cuda" and has_cuda is not None and not has_cuda():
        return False, ("our extension was built without CUDA (native._backend.has_cuda() is "
                       "False: check nvcc / CUDA_HOME, and DGS_CUDA)"), secs
    try:
        s = on_device(surface_scene(2000, 64, 48), DEVICE)
        out = native.rasterize(s.means, s.quats, s.scales, s.opacity_c, s.opacity_g, s.colors,
                               s.geometry, s.viewmat, s.K, s.width, s.height, beta=BETA_FUSED,
                               eps2d=EPS2D, antialiased=False, validate=True)
        torch.cuda.synchronize()
        if out.color.device.type != "cuda":
            return False, f"our rasterizer returned {out.color.device} tensors for CUDA input", secs
    except Exception as exc:  # noqa: BLE001
        return False, f"our rasterizer does not run on CUDA: {_short(exc)}", secs
    return True, "ok", secs


def load_gsplat(disabled: bool) -> tuple[object | None, str, float]:
    """(module or None, note, build seconds). Triggers gsplat's JIT build with a tiny call."""
    import torch

    if disabled:
        return None, "disabled by --no-gsplat", 0.0
    extracted = _extract_wheels()
    try:
        import gsplat
    except Exception as exc:  # noqa: BLE001
        return None, f"gsplat cannot be imported: {_short(exc)}", 0.0
    note = f"gsplat {getattr(gsplat, '__version__', '?')}"
    if extracted:
        note += " (" + "; ".join(extracted) + ")"
    t0 = time.perf_counter()
    try:
        from gsplat.cuda._backend import _C

        if _C is None:
            return None, note + ": its CUDA backend is unavailable (no CUDA toolkit found)", \
                time.perf_counter() - t0
        s = on_device(surface_scene(2000, 64, 48), DEVICE)
        colors, alphas, _ = gsplat.rasterization(
            s.means, s.quats, s.scales, s.opacity_c, s.colors, s.viewmat[None], s.K[None],
            s.width, s.height, **gsplat_kwargs(None, "RGB"))
        torch.cuda.synchronize()
    except Exception as exc:  # noqa: BLE001
        tail = "\n".join(str(exc).strip().splitlines()[-40:])
        print(f"gsplat's JIT build or first call failed; the end of its message:\n{tail}",
              file=sys.stderr, flush=True)
        return None, note + f": JIT build or first call failed: {_short(exc)}", \
            time.perf_counter() - t0
    return gsplat, note, time.perf_counter() - t0


def gsplat_kwargs(packed: bool | None, render_mode: str) -> dict:
    kw = dict(near_plane=NEAR, far_plane=FAR, eps2d=EPS2D, tile_size=TILE, sh_degree=None,
              rasterize_mode="classic", render_mode=render_mode)
    if packed is not None:
        kw["packed"] = packed
    return kw


def _short(exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}".strip()
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if len(lines) > 6:
        lines = lines[:3] + ["..."] + lines[-3:]
    return " | ".join(lines)[:1500]


# ----------------------------------------------------------------------------------- cells


def _weights(width: int, height: int, device, seed: int) -> dict:
    """Fixed random weight images, one per output (the loss is sum(output * weight))."""
    import torch

    g = torch.Generator(device=device).manual_seed(seed)

    def w(ch):
        return torch.rand(height, width, ch, generator=g, device=device) + 0.5

    ws = {"color": w(C_APPEAR), "alpha_c": w(1), "geometry": w(G_GEOM), "depth": w(1),
          "alpha_g": w(1)}
    ws["geometry+depth"] = torch.cat([ws["geometry"], ws["depth"]], -1).contiguous()
    return ws


def make_cell(cell: str, s: Scene, ws: dict, gs, packed: bool | None):
    """(forward() -> list of (output, weight), leaves that receive gradients)."""
    per_gauss = [s.means, s.quats, s.scales, s.opacity_c, s.colors]
    if cell in ("a", "b"):
        import native

        fused = cell == "a"

        def forward():
            out = native.rasterize(
                s.means, s.quats, s.scales, s.opacity_c, s.opacity_g if fused else s.opacity_c,
                s.colors, s.geometry if fused else None, s.viewmat, s.K, s.width, s.height,
                beta=BETA_FUSED if fused else 0.0, eps2d=EPS2D, antialiased=False, near=NEAR,
                far=FAR, validate=False)
            pairs = [(out.color, ws["color"]), (out.alpha_c, ws["alpha_c"])]
            if fused:
                pairs += [(out.geometry, ws["geometry"]), (out.depth, ws["depth"]),
                          (out.alpha_g, ws["alpha_g"])]
            return pairs

        return forward, per_gauss + ([s.opacity_g, s.geometry] if fused else [])

    twice = cell == "d"
    vm, K = s.viewmat[None].contiguous(), s.K[None].contiguous()

    def forward():
        col, alph, _ = gs.rasterization(s.means, s.quats, s.scales, s.opacity_c, s.colors, vm, K,
                                        s.width, s.height, **gsplat_kwargs(packed, "RGB"))
        pairs = [(col[0], ws["color"]), (alph[0], ws["alpha_c"])]
        if twice:
            geo, alph_g, _ = gs.rasterization(s.means, s.quats, s.scales, s.opacity_g, s.geometry,
                                              vm, K, s.width, s.height,
                                              **gsplat_kwargs(packed, "RGB+ED"))
            pairs += [(geo[0], ws["geometry+depth"]), (alph_g[0], ws["alpha_g"])]
        return pairs

    return forward, per_gauss + ([s.opacity_g, s.geometry] if twice else [])


def _loss(pairs):
    total = None
    for out, w in pairs:
        term = (out * w).sum()
        total = term if total is None else total + term
    return total


def measure(forward, leaves, iters: int, warmup: int) -> dict:
    import torch

    def zero():
        for t in leaves:
            t.grad = None

    def step():
        _loss(forward()).backward()

    for _ in range(warmup):
        zero()
        step()
    zero()
    torch.cuda.synchronize()
    gc.collect()
    base = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    step()
    torch.cuda.synchronize()
    peak = torch.cuda.max_memory_allocated() - base
    full, full_wall = [], []
    for _ in range(iters):
        zero()
        torch.cuda.synchronize()
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        t0 = time.perf_counter()
        a.record()
        step()
        b.record()
        b.synchronize()
        full_wall.append(1e3 * (time.perf_counter() - t0))
        full.append(a.elapsed_time(b))
    zero()
    fwd = []
    with torch.no_grad():
        for _ in range(max(1, warmup)):
            out = forward()
            del out
        for _ in range(iters):
            torch.cuda.synchronize()
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            out = forward()
            b.record()
            b.synchronize()
            del out
            fwd.append(a.elapsed_time(b))
    return {"status": "ok", "fwd_bwd_ms": statistics.median(full), "fwd_ms": statistics.median(fwd),
            "peak_mb": peak / 2**20, "fwd_bwd_ms_all": full, "fwd_ms_all": fwd,
            "fwd_bwd_wall_ms_all": full_wall, "baseline_mb": base / 2**20}


def run_cell(cell, s, ws, gs, packed, iters, warmup) -> dict:
    import torch

    result: dict
    leaves = []
    try:
        forward, leaves = make_cell(cell, s, ws, gs, packed)
        result = measure(forward, leaves, iters, warmup)
    except torch.cuda.OutOfMemoryError as exc:
        result = {"status": "oom", "error": _short(exc)}
    except Exception as exc:  # noqa: BLE001
        result = {"status": "error", "error": _short(exc),
                  "traceback": traceback.format_exc()[-3000:]}
    for t in leaves:
        t.grad = None
    forward = None  # noqa: F841
    gc.collect()
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    return result


def scene_stats(s: Scene, ours_ok: bool, gs, packed) -> dict:
    """Visible Gaussians (ours: radii > 0) and (gsplat) Gaussian-tile pairs per tile."""
    import torch

    stats = {}
    with torch.no_grad():
        try:
            if not ours_ok:
                raise RuntimeError("ours unavailable")
            import native

            out = native.rasterize(s.means, s.quats, s.scales, s.opacity_c, s.opacity_g,
                                   s.colors, s.geometry, s.viewmat, s.K, s.width, s.height,
                                   beta=BETA_FUSED, eps2d=EPS2D, validate=False)
            stats["visible_ours"] = int((out.radii > 0).sum())
            stats["mean_alpha_c"] = float(out.alpha_c.mean())
            del out
        except Exception:  # noqa: BLE001
            pass
        if gs is not None:
            try:
                _, alph, meta = gs.rasterization(s.means, s.quats, s.scales, s.opacity_c, s.colors,
                                                 s.viewmat[None], s.K[None], s.width, s.height,
                                                 **gsplat_kwargs(packed, "RGB"))
                tiles = int(meta["tile_width"]) * int(meta["tile_height"])
                stats["tile_pairs_gsplat"] = int(meta["flatten_ids"].numel())
                stats["pairs_per_tile_gsplat"] = stats["tile_pairs_gsplat"] / max(tiles, 1)
                stats["mean_alpha_gsplat"] = float(alph.mean())
                del meta, alph
            except Exception:  # noqa: BLE001
                pass
    return stats


# ----------------------------------------------------------------------------------- output


def _size_label(n: int) -> str:
    if n >= 1_000_000 and n % 1_000_000 == 0:
        return f"{n // 1_000_000}M"
    if n >= 1000 and n % 1000 == 0:
        return f"{n // 1000}k"
    return str(n)


def parse_sizes(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        p = part.strip().lower().replace("_", "")
        if not p:
            continue
        mult = 1
        if p.endswith("k"):
            mult, p = 1000, p[:-1]
        elif p.endswith("m"):
            mult, p = 1_000_000, p[:-1]
        out.append(int(float(p) * mult))
    if not out:
        raise argparse.ArgumentTypeError("no sizes given")
    return out


def parse_res(text: str) -> tuple[int, int]:
    try:
        w, h = text.lower().split("x")
        return int(w), int(h)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"resolution must look like 1920x1080, got {text}") \
            from exc


def _cell_text(r: dict | None, key: str, fmt: str = "{:.2f}") -> str:
    if r is None:
        return "-"
    if r.get("status") != "ok":
        return r.get("status", "-")
    return fmt.format(r[key])


def _ratio(a: dict | None, b: dict | None, key: str = "fwd_bwd_ms") -> float | None:
    if not a or not b or a.get("status") != "ok" or b.get("status") != "ok":
        return None
    return a[key] / b[key]


def _rtext(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}x"


def tables(report: dict) -> tuple[str, str, list[str]]:
    """(forward-only table, main table, target lines)."""
    res = report["results"]
    st = report["settings"]
    head = (f"{st['width']}x{st['height']}, C={C_APPEAR}, G={G_GEOM}, {report['device']}; "
            f"median of {st['iters']} after {st['warmup']} warm-up; ours: tile {TILE}, "
            f"eps2d {EPS2D}, near {NEAR}, far {FAR:g}, antialiased=False, beta {BETA_FUSED} fused "
            f"/ 0 appearance-only; gsplat {report.get('gsplat_version') or 'n/a'}: "
            f"rasterization(tile_size={TILE}, eps2d={EPS2D}, near_plane={NEAR}, "
            f"far_plane={FAR:g}, rasterize_mode='classic', sh_degree=None, "
            f"packed={st['packed_text']}), render_mode 'RGB' (3 ch) and 'RGB+ED' (5+1 ch, "
            f"which gsplat pads to 8)")
    fwd_lines = [f"### Forward only (no_grad), ms — {head}", "",
                 "| N | (a) ours fused | (b) ours appearance | (c) gsplat RGB | (d) gsplat twice "
                 "| (a)/(c) | (a)/(d) |", "|---|---|---|---|---|---|---|"]
    main = [f"### Forward+backward, ms, and peak GPU MB above inputs — {head}", "",
            "| N | (a) ours fused | (b) ours appearance | (c) gsplat RGB | (d) gsplat twice "
            "| (a)/(c) | (a)/(d) | (b)/(c) | peak MB (a) | (b) | (c) | (d) | pairs/tile |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for n_text, row in res.items():
        c = row.get("cells", {})
        fwd_lines.append(
            f"| {n_text} | " + " | ".join(_cell_text(c.get(k), "fwd_ms") for k in CELLS)
            + f" | {_rtext(_ratio(c.get('a'), c.get('c'), 'fwd_ms'))} "
            f"| {_rtext(_ratio(c.get('a'), c.get('d'), 'fwd_ms'))} |")
        ppt = row.get("stats", {}).get("pairs_per_tile_gsplat")
        main.append(
            f"| {n_text} | " + " | ".join(_cell_text(c.get(k), "fwd_bwd_ms") for k in CELLS)
            + f" | {_rtext(_ratio(c.get('a'), c.get('c')))} "
            f"| {_rtext(_ratio(c.get('a'), c.get('d')))} "
            f"| {_rtext(_ratio(c.get('b'), c.get('c')))} | "
            + " | ".join(_cell_text(c.get(k), "peak_mb", "{:.0f}") for k in CELLS)
            + f" | {'-' if ppt is None else f'{ppt:.0f}'} |")
    targets = []
    one_m = res.get("1M")
    if one_m is None:
        targets.append("Targets at 1M: not measured (1M not in --sizes).")
    else:
        c = one_m.get("cells", {})
        for label, other, limit in (("gsplat RGB-only (c)", "c", TARGET_RGB),
                                    ("gsplat twice (d)", "d", TARGET_TWICE)):
            r = _ratio(c.get("a"), c.get(other))
            verdict = "unknown (a cell is missing)" if r is None else (
                "MET" if r <= limit else "NOT MET")
            targets.append(f"Target at 1M: ours fused <= {limit:.2f}x {label}: "
                           f"{_rtext(r)} -> {verdict}")
    return "\n".join(fwd_lines), "\n".join(main), targets


def write_json(report: dict, path: Path | None) -> None:
    if path is None:
        return
    fwd, main, targets = tables(report)
    report = dict(report, table_markdown=main, forward_table_markdown=fwd, targets=targets)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(report, indent=1))
    os.replace(tmp, path)


# ----------------------------------------------------------------------------------- check


def rel_err(a, b) -> float:
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    if b.numel() == 0:
        return 0.0
    scale = float(b.abs().max())
    diff = float((a - b).abs().max())
    return diff / scale if scale > 0 else diff


def _px_off(a, b, tol=1e-3) -> int:
    """Pixels of an (H, W, k) image where some channel differs by more than tol * max|b|."""
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    if b.numel() == 0:
        return 0
    scale = float(b.abs().max()) or 1.0
    return int(((a - b).abs().amax(-1) > tol * scale).sum())


def run_check(args, gs) -> list[str]:
    import torch

    import native

    W, H = args.check_res
    lines = [f"### Our CUDA path vs our CPU path ({args.check_n:,} Gaussians, {W}x{H}): max "
             "relative error = max|cuda - cpu| / max|cpu|", "",
             "| scene | dtype | branches | worst output | worst fwd err | px off >1e-3 "
             "| radii mismatches | worst grad | worst grad err | within tol |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    details = {}
    image_outputs = ("color", "geometry", "depth", "alpha_c", "alpha_g")
    other_outputs = ("means2d", "contribution")
    for scene_name, make in (("surface", surface_scene), ("volume", volume_scene)):
        base = make(args.check_n, W, H, C=C_APPEAR, G=G_GEOM, seed=args.seed + 7)
        for dtype in (torch.float32, torch.float64):
            for fused in (True, False):
                key = f"{scene_name}/{str(dtype)[6:]}/{'fused' if fused else 'appearance'}"
                try:
                    outs, grads = {}, {}
                    for side, dev in (("cpu", "cpu"), ("cuda", DEVICE)):
                        s = on_device(base, dev, dtype, grad="all")
                        out = native.rasterize(
                            s.means, s.quats, s.scales, s.opacity_c, s.opacity_g, s.colors,
                            s.geometry if fused else None, s.viewmat, s.K, W, H,
                            beta=BETA_FUSED, eps2d=EPS2D, antialiased=False, validate=True)
                        g = torch.Generator().manual_seed(args.seed + 11)
                        loss = 0
                        for name in image_outputs:
                            t = getattr(out, name)
                            w = torch.rand(t.shape, generator=g, dtype=dtype).to(dev)
                            loss = loss + (t * w).sum()
                        loss.backward()
                        outs[side] = {n: getattr(out, n).detach() for n in
                                     image_outputs + other_outputs + ("radii", "absgrad_c",
                                                                      "absgrad_g")}
                        grads[side] = {f.name: getattr(s, f.name).grad for f in fields(s)
                                      if isinstance(getattr(s, f.name), torch.Tensor)
                                      and getattr(s, f.name).grad is not None}
                    fwd_err = {n: rel_err(outs["cuda"][n], outs["cpu"][n])
                               for n in image_outputs + other_outputs + ("absgrad_c", "absgrad_g")}
                    px = max(_px_off(outs["cuda"][n], outs["cpu"][n]) for n in image_outputs)
                    radii_bad = int((outs["cuda"]["radii"].cpu() != outs["cpu"]["radii"]).sum())
                    grad_err = {n: rel_err(grads["cuda"][n], grads["cpu"][n])
                                for n in grads["cpu"]}
                    missing = sorted(set(grads["cpu"]) ^ set(grads["cuda"]))
                    wf = max(fwd_err, key=fwd_err.get)
                    wg = max(grad_err, key=grad_err.get) if grad_err else "-"
                    tol_f, tol_g = (1e-4, 2e-3) if dtype == torch.float32 else (1e-10, 1e-10)
                    ok = (fwd_err[wf] <= tol_f and (not grad_err or grad_err[wg] <= tol_g)
                          and radii_bad == 0 and not missing)
                    details[key] = {"forward": fwd_err, "grads": grad_err, "px_off": px,
                                    "radii_mismatches": radii_bad, "grad_missing": missing}
                    lines.append(
                        f"| {scene_name} | {str(dtype)[6:]} | {'fused' if fused else 'appearance'}"
                        f" | {wf} | {fwd_err[wf]:.2e} | {px} | {radii_bad} | {wg} | "
                        f"{grad_err.get(wg, 0.0):.2e} | "
                        f"{'yes' if ok else 'NO'} (fwd {tol_f:g}, grad {tol_g:g})"
                        f"{'; grads missing on one side: ' + ','.join(missing) if missing else ''}"
                        " |")
                except Exception as exc:  # noqa: BLE001
                    details[key] = {"error": _short(exc)}
                    lines.append(f"| {scene_name} | {str(dtype)[6:]} | "
                                 f"{'fused' if fused else 'appearance'} | error: {_short(exc)} "
                                 "| | | | | | |")
                    traceback.print_exc()
                gc.collect()
                torch.cuda.empty_cache()
    lines.append("")
    lines.append("Per-output and per-gradient errors (float32, surface, fused): " + json.dumps(
        {k: (f"{v:.1e}" if isinstance(v, float) else v)
         for k, v in {**details.get("surface/float32/fused", {}).get("forward", {}),
                      **{"grad_" + k: v for k, v in
                         details.get("surface/float32/fused", {}).get("grads", {}).items()}
                      }.items()}))
    if gs is not None:
        lines += ["", _gsplat_cross_check(args, gs)]
    args._check_details = details
    return lines


def _gsplat_cross_check(args, gs) -> str:
    """Ours appearance-only (beta 0, opacity_g = opacity_c) against gsplat RGB, same scene."""
    import torch

    import native

    W, H = args.check_res
    try:
        s = on_device(surface_scene(args.check_n, W, H, seed=args.seed + 7), DEVICE)
        with torch.no_grad():
            ours = native.rasterize(s.means, s.quats, s.scales, s.opacity_c, s.opacity_c,
                                    s.colors, None, s.viewmat, s.K, W, H, beta=0.0, eps2d=EPS2D,
                                    antialiased=False, validate=True)
            col, alph, _ = gs.rasterization(s.means, s.quats, s.scales, s.opacity_c, s.colors,
                                            s.viewmat[None], s.K[None], W, H,
                                            **gsplat_kwargs(None, "RGB"))
        dc = (ours.color - col[0]).abs()
        da = (ours.alpha_c - alph[0]).abs()
        return (f"Ours appearance-only vs gsplat RGB on the surface scene (informational; gsplat "
                f"clamps alpha at 0.999 and uses fast math, ours 0.99): color |diff| mean "
                f"{float(dc.mean()):.2e} max {float(dc.max()):.2e}, alpha mean "
                f"{float(da.mean()):.2e} max {float(da.max()):.2e}, pixels with color diff > 1e-2: "
                f"{int((dc.amax(-1) > 1e-2).sum())} of {W * H}")
    except Exception as exc:  # noqa: BLE001
        return f"Ours vs gsplat cross-check failed: {_short(exc)}"


# ----------------------------------------------------------------------------------- main


def profile_cells(cells, s, ws, gs, packed, steps: int = 5, top: int = 14) -> str:
    """Per-kernel GPU time of forward+backward (torch.profiler, `steps` steps after a warm-up),
    the `top` kernels by total time, for each cell: where the time of a cell goes."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    parts = []
    for cell in cells:
        if (cell in "cd" and gs is None):
            continue
        forward, leaves = make_cell(cell, s, ws, gs, packed)
        for _ in range(2):
            _loss(forward()).backward()
        torch.cuda.synchronize()
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for _ in range(steps):
                for t in leaves:
                    t.grad = None
                _loss(forward()).backward()
            torch.cuda.synchronize()
        rows = [e for e in prof.key_averages() if e.device_type.name == "CUDA"]
        rows.sort(key=lambda e: -e.self_device_time_total)
        total = sum(e.self_device_time_total for e in rows) / steps / 1e3
        lines = [f"({cell}) {CELL_NAMES[cell]}: GPU kernel time {total:.2f} ms per step",
                 "| kernel | ms/step | calls/step |", "|---|---|---|"]
        for e in rows[:top]:
            lines.append(f"| {e.key[:90]} | {e.self_device_time_total / steps / 1e3:.3f} | "
                         f"{e.count / steps:.0f} |")
        parts.append("\n".join(lines))
        for t in leaves:
            t.grad = None
    return "\n\n".join(parts)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sizes", type=parse_sizes, default=parse_sizes("100k,1M,3M"),
                    help="Gaussian counts, comma-separated, k/M suffixes (default 100k,1M,3M)")
    ap.add_argument("--res", type=parse_res, default=(1920, 1080), help="WxH (default 1920x1080)")
    ap.add_argument("--iters", type=int, default=20, help="timed iterations per cell (default 20)")
    ap.add_argument("--warmup", type=int, default=3, help="warm-up iterations (default 3)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cells", default="abcd", help="which of a,b,c,d to run (default abcd)")
    ap.add_argument("--packed", choices=["default", "true", "false"], default="default",
                    help="gsplat's packed argument (default: gsplat's own default)")
    ap.add_argument("--no-gsplat", action="store_true", help="measure ours only")
    ap.add_argument("--out", type=Path, default=None,
                    help="write the table and raw numbers as JSON here (after every cell)")
    ap.add_argument("--budget-s", type=float, default=0.0,
                    help="stop starting cells after this many seconds from start (0: no limit); "
                         "the rest read 'skipped'")
    ap.add_argument("--check", action="store_true",
                    help="compare our CUDA path with our CPU path on small scenes (and exit, "
                         "unless --bench)")
    ap.add_argument("--bench", action="store_true", help="with --check: also run the benchmark")
    ap.add_argument("--check-n", type=parse_sizes, default=[20_000],
                    help="Gaussians in the --check scenes (default 20k)")
    ap.add_argument("--check-res", type=parse_res, default=(320, 240),
                    help="--check image size (default 320x240)")
    ap.add_argument("--profile", action="store_true",
                    help="per-kernel GPU time of each cell at the first size (torch.profiler), "
                         "instead of the timing table")
    ap.add_argument("--build-only", action="store_true",
                    help="build our extension and gsplat's, report, and exit")
    args = ap.parse_args()
    args.check_n = args.check_n[0]
    t_start = time.perf_counter()

    try:
        import torch
    except ImportError:
        print("torch is not installed; this benchmark needs torch with CUDA.", file=sys.stderr)
        return 2
    if not torch.cuda.is_available():
        print("CUDA is needed: torch.cuda.is_available() is False on this machine "
              f"(torch {torch.__version__}, CUDA build {torch.version.cuda}). Nothing measured.",
              file=sys.stderr)
        return 2
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    _prepare_env()

    cells = [c for c in CELLS if c in args.cells]
    want_gsplat = not args.no_gsplat and (args.check or any(c in cells for c in "cd")
                                          or args.build_only)
    packed = None if args.packed == "default" else args.packed == "true"
    dev_name = torch.cuda.get_device_name(0)
    print(f"device: {dev_name}, torch {torch.__version__} (CUDA {torch.version.cuda}), "
          f"python {platform.python_version()}, MAX_JOBS={os.environ.get('MAX_JOBS')}, "
          f"TORCH_CUDA_ARCH_LIST={os.environ.get('TORCH_CUDA_ARCH_LIST')}", flush=True)

    native_proc = _start_native_build()
    gs, gs_note, gs_secs = load_gsplat(not want_gsplat)
    print(f"gsplat: {gs_note if gs is None else gs_note + ' ok'} ({gs_secs:.0f} s)", flush=True)
    ours_ok, ours_note, ours_secs = load_ours(native_proc)
    print(f"ours: {ours_note} ({ours_secs:.0f} s waiting for/loading the build)", flush=True)
    if args.build_only:
        return 0 if ours_ok and (gs is not None or not want_gsplat) else 1

    if args.check:
        if not ours_ok:
            print("--check needs our rasterizer on CUDA: " + ours_note)
            return 1
        lines = run_check(args, gs)
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            cpath = args.out.with_name(args.out.stem + "_check.json") if args.bench else args.out
            cpath.write_text(json.dumps({"check": args._check_details, "lines": lines}, indent=1))
        print("\n" + "\n".join(lines), flush=True)
        if not args.bench:
            return 0

    W, H = args.res
    report = {
        "device": dev_name, "torch": torch.__version__, "cuda": torch.version.cuda,
        "gsplat_version": getattr(gs, "__version__", None) if gs is not None else None,
        "gsplat_note": gs_note, "ours_note": ours_note,
        "build_s": {"gsplat": gs_secs, "ours_wait": ours_secs},
        "settings": {"width": W, "height": H, "iters": args.iters, "warmup": args.warmup,
                     "seed": args.seed, "C": C_APPEAR, "G": G_GEOM, "eps2d": EPS2D,
                     "near": NEAR, "far": FAR, "tile": TILE, "beta_fused": BETA_FUSED,
                     "packed_text": "default" if packed is None else str(packed),
                     "scene": "surface_scene (bench_scenes.py), layers=3, 5% floaters",
                     "tf32": False},
        "cells": CELL_NAMES, "results": {},
    }
    for n in args.sizes:
        label = _size_label(n)
        row = report["results"].setdefault(label, {"n": n, "cells": {}, "stats": {}})
        t0 = time.perf_counter()
        try:
            s = on_device(surface_scene(n, W, H, C=C_APPEAR, G=G_GEOM, seed=args.seed), DEVICE,
                          grad=True)
            ws = _weights(W, H, DEVICE, args.seed + 1)
        except torch.cuda.OutOfMemoryError:
            for c in cells:
                row["cells"][c] = {"status": "oom", "error": "building the scene"}
            gc.collect()
            torch.cuda.empty_cache()
            continue
        row["scene_s"] = time.perf_counter() - t0
        if args.profile:
            print(f"\nprofile, N={label}, {W}x{H}:\n" + profile_cells(cells, s, ws, gs, packed),
                  flush=True)
            return 0
        row["stats"] = scene_stats(s, ours_ok, gs, packed)
        print(f"\nN={label}: scene {row['scene_s']:.1f} s, stats {row['stats']}", flush=True)
        for c in cells:
            if args.budget_s and time.perf_counter() - t_start > args.budget_s:
                row["cells"][c] = {"status": "skipped", "error": "--budget-s reached"}
                continue
            if c in "ab" and not ours_ok:
                row["cells"][c] = {"status": "n/a", "error": ours_note}
                continue
            if c in "cd" and gs is None:
                row["cells"][c] = {"status": "n/a", "error": gs_note}
                continue
            r = run_cell(c, s, ws, gs, packed, args.iters, args.warmup)
            row["cells"][c] = r
            msg = (f"fwd+bwd {r['fwd_bwd_ms']:.2f} ms, fwd {r['fwd_ms']:.2f} ms, "
                   f"peak {r['peak_mb']:.0f} MB" if r["status"] == "ok"
                   else f"{r['status']}: {r.get('error', '')}")
            print(f"  ({c}) {CELL_NAMES[c]}: {msg}", flush=True)
            write_json(report, args.out)
        del s, ws
        gc.collect()
        torch.cuda.empty_cache()
        write_json(report, args.out)

    fwd, main_table, targets = tables(report)
    notes = []
    if not ours_ok:
        notes.append("ours not measured: " + ours_note.splitlines()[0][:300])
    if gs is None:
        notes.append("gsplat not measured: " + gs_note[:300])
    print("\n" + fwd + "\n")
    if notes:
        print("\n".join(notes) + "\n")
    print(main_table + "\n")
    print("\n".join(targets))
    if args.out is not None:
        print(f"(JSON: {args.out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
