"""The importers on mutated files (issue 42): every reader (panoptic, transforms, COLMAP text
and binary, IDR, ActorsHQ, and canonical capture.json validation) run on `--examples` mutated
copies of a small valid source in all (tests/fuzz_sources.py), counting what each did:
imported, refused with a CaptureError naming the file, or anything else (unexpected: a bug).
Every `--api-every`-th input also goes to `POST /v1/captures/archive?format=<reader>` of an
in-process app (embedded defaults), counting the statuses: a 5xx is a failure. Then the
`--big-frames` cases: a train_meta.json of that many frames (a comma-separated list), each
read in a child process, timed, with its peak memory.

    python benchmarks/fuzz_importers.py --examples 10000 [--api-every 10] [--seed 0]
        [--root REPO] [--big-frames 47000,60000,1000000] [--out results.json]

`--root` runs another checkout's importers and app the same way (its own `core` and
`service`; the mutations are this repository's). Exits 1 when anything unexpected happened.
"""

from __future__ import annotations

import argparse
import collections
import io
import json
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIG = """
import json, sys, time
from pathlib import Path
from core.data import CaptureError
from core.data.importers.panoptic import read_panoptic
t = time.perf_counter()
try:
    read_panoptic(Path(sys.argv[1]))
    what = "imported"
except CaptureError as exc:
    what = "CaptureError: " + exc.problems[0].message[:120]
except Exception as exc:
    what = type(exc).__name__ + ": " + str(exc)[:120]
# VmHWM, not ru_maxrss: Linux carries the forking parent's peak into a child's ru_maxrss.
hwm = next(l for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print(json.dumps({"seconds": time.perf_counter() - t, "what": what,
                  "peak_mb": int(hwm.split()[1]) / 1024}))
"""


def _zip(folder: Path) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            zf.write(path, path.relative_to(folder).as_posix())
    return buf.getvalue()


def _app(data: Path):
    from fastapi.testclient import TestClient

    sys.path.insert(0, str(ROOT / "tests" / "service"))
    from service_harness import make_settings

    from service.app import create_app

    return TestClient(create_app(make_settings(data)), raise_server_exceptions=False)


def fuzz(work: Path, examples: int, api_every: int, seed: int) -> dict:
    """Counts per source kind of importer outcomes and API statuses; the first few
    unexpected outcomes in full."""
    from fuzz_sources import READER, make_sources, mutated_copy, run_importer

    from core.synth import SynthConfig, synthesize

    capture = work / "capture"
    synthesize(capture, SynthConfig(frames=2, views=3, width=16, height=16, seed=1,
                                    ao_directions=4, supersample=1))
    sources = make_sources(capture, work / "sources")
    kinds = sorted(sources)
    counts: dict[str, collections.Counter] = {k: collections.Counter() for k in kinds}
    unexpected: list[dict] = []
    errors: collections.Counter = collections.Counter()  # what escaped, by exception type
    client = _app(work / "data") if api_every else None
    for i in range(examples):
        kind = kinds[i % len(kinds)]
        case = work / "case"
        shutil.rmtree(case, ignore_errors=True)
        folder, done = mutated_copy(sources[kind], case / "src", seed + i)
        outcome, what = run_importer(sources[kind], folder, case / "out")
        counts[kind][outcome] += 1
        if outcome == "unexpected":
            errors[what.split("\n", 1)[0]] += 1
        if outcome == "unexpected" and len(unexpected) < 20:
            unexpected.append({"kind": kind, "seed": seed + i, "mutations": done, "what": what})
        if client is not None and i % api_every == 0:
            fmt = "canonical" if kind == "canonical" else READER.get(kind, kind)
            r = client.post("/v1/captures/archive", params={"format": fmt},
                            content=_zip(folder), headers={"Content-Type": "application/zip"})
            error = r.json().get("error", {}) if r.status_code >= 400 else {}
            counts[kind][f"api {r.status_code}"] += 1
            if r.status_code >= 500 and len(unexpected) < 20:
                unexpected.append({"kind": kind, "seed": seed + i, "mutations": done,
                                   "what": f"{r.status_code} {error}"})
        if (i + 1) % 500 == 0:
            print(f"  {i + 1} / {examples}", file=sys.stderr, flush=True)
    return {"counts": {k: dict(v) for k, v in counts.items()}, "unexpected": unexpected,
            "errors": dict(errors.most_common())}


def big_meta(work: Path, frames: int, root: Path) -> dict:
    """A train_meta.json of `frames` frames of one camera (ims/ left out: it is refused or
    read before any image is), read by `root`'s importer in a child process."""
    src = work / f"big-{frames}"
    src.mkdir()
    K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    E = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]
    with open(src / "train_meta.json", "w") as f:
        f.write('{"w":640,"h":480,"k":[')
        f.write(",".join([json.dumps([K], separators=(",", ":"))] * frames))
        f.write('],"w2c":[' + ",".join([json.dumps([E], separators=(",", ":"))] * frames))
        f.write('],"fn":[' + ",".join(f'["0/{t:06d}.jpg"]' for t in range(frames)))
        f.write('],"cam_id":[' + ",".join(["[0]"] * frames) + "]}")
    size = (src / "train_meta.json").stat().st_size
    out = subprocess.run([sys.executable, "-c", BIG, str(src)], cwd=root, capture_output=True,
                         text=True, timeout=1800, env={"PYTHONPATH": str(root), "PATH": ""})
    if out.returncode != 0:
        return {"frames": frames, "bytes": size, "error": out.stderr[-2000:]}
    return {"frames": frames, "bytes": size, **json.loads(out.stdout.strip().splitlines()[-1])}


def _table(counts: dict[str, dict]) -> str:
    cols = sorted({c for v in counts.values() for c in v},
                  key=lambda c: (c.startswith("api"), c))
    lines = ["| source | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for kind, row in counts.items():
        lines.append(f"| {kind} | " + " | ".join(str(row.get(c, 0)) for c in cols) + " |")
    total = collections.Counter()
    for row in counts.values():
        total.update(row)
    lines.append("| all | " + " | ".join(str(total.get(c, 0)) for c in cols) + " |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--examples", type=int, default=10_000, help="mutated inputs in all")
    parser.add_argument("--api-every", type=int, default=10,
                        help="every N-th input also through the archive route (0: none)")
    parser.add_argument("--seed", type=int, default=0, help="first seed")
    parser.add_argument("--root", type=Path, default=ROOT, help="checkout whose code to run")
    parser.add_argument("--big-frames", default="",
                        help="also read train_meta.json files of these many frames (1,2,...)")
    parser.add_argument("--out", type=Path, help="write the results here as JSON")
    args = parser.parse_args()
    sys.path[:0] = [str(args.root.resolve()), str(ROOT / "tests")]
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="dgs-fuzz-") as tmp:
        result = fuzz(Path(tmp), args.examples, args.api_every, args.seed)
        result["big"] = [big_meta(Path(tmp), int(n), args.root.resolve())
                         for n in args.big_frames.split(",") if n]
    result["seconds"] = round(time.perf_counter() - started, 1)
    print(_table(result["counts"]))
    for case in result["unexpected"]:
        print(f"\n--- {case['kind']} seed {case['seed']} {case['mutations']}\n{case['what']}")
    if result["errors"]:
        print("\nunexpected, by type:", json.dumps(result["errors"]))
    for big in result["big"]:
        print("\nbig train_meta.json:", json.dumps(big))
    print(f"\n{result['seconds']} s")
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))
    bad = sum(v.get("unexpected", 0) + sum(n for c, n in v.items() if c.startswith("api 5"))
              for v in result["counts"].values())
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
