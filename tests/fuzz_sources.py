"""Mutated capture sources for the importers' fuzz test (tests/core/test_importers_fuzz.py) and
its long run (benchmarks/fuzz_importers.py): one small valid source per reader, and mutations
of its metadata files that know each file's form (a JSON tree, CSV cells, text tokens, binary
records, npz arrays) besides blind byte damage. Every mutation is drawn from one seed, so a
failure names the seed that reproduces it."""

from __future__ import annotations

import csv
import io
import json
import os
import random
import shutil
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ATTACKS: tuple = (
    None, True, False, 0, -1, 1, 3, 2**31, 2**63, 10**30, -(10**40), 10**400, 1.5, -0.0,
    1e308, -1e308, 5e-324, float("nan"), float("inf"), "", "0", "1.5", "nan", " 12", "1_000",
    "../x", "../1/000000.png", "../../etc/passwd", "/etc/000000.png", "C:\\x.png", "a\\b.png",
    "камера", "кадр0", "Ⅻ0", "٣", "\x00", "a\x1b[2J", "\u202e", "a" * 300, "x/" * 40 + "y",
    "a/b/c.png", ".", "..", "./", "images", "ims", "rgbs", "sparse", [], {}, [[]], [[], []],
    [1, 2, 3], [[1, 2], [3]], {"a": 1}, [None], ["x"], [[[[[[[[[[[]]]]]]]]]]],
)
"""Values a hostile client would try: wrong types, extremes, paths out, names outside ASCII."""


@dataclass(frozen=True)
class Source:
    """A valid source folder and what of it may be mutated."""

    fmt: str
    """Its format as `core.data.importers` names it, or "canonical"."""
    root: Path
    files: tuple[str, ...]
    """Metadata files (relative to `root`), the ones mutated."""


def make_sources(capture: Path, dest: Path) -> dict[str, Source]:
    """Every reader's source, exported from the canonical `capture` under `dest`."""
    from core.data import load_capture
    from core.data.importers.actorshq import export_actorshq
    from core.data.importers.colmap import export_colmap
    from core.data.importers.idr import export_idr
    from core.data.importers.panoptic import export_panoptic
    from core.data.importers.transforms import export_transforms

    cap = load_capture(capture)
    export_panoptic(cap, dest / "panoptic", test_cameras=[cap.cameras[0].id])
    export_transforms(cap, dest / "transforms")
    export_colmap(cap, dest / "colmap-text")
    export_colmap(cap, dest / "colmap-binary", binary=True)
    export_idr(cap, dest / "idr")
    export_actorshq(cap, dest / "actorshq")
    shutil.copytree(capture, dest / "canonical", ignore=shutil.ignore_patterns("gt", "source"))
    model = "sparse/0/"
    return {s.fmt: s for s in (
        Source("panoptic", dest / "panoptic", ("train_meta.json", "test_meta.json")),
        Source("transforms", dest / "transforms", ("transforms.json",)),
        Source("colmap-text", dest / "colmap-text",
               tuple(model + f for f in ("cameras.txt", "images.txt", "points3D.txt"))),
        Source("colmap-binary", dest / "colmap-binary",
               tuple(model + f for f in ("cameras.bin", "images.bin", "points3D.bin"))),
        Source("idr", dest / "idr", ("cameras.npz",)),
        Source("actorshq", dest / "actorshq", ("calibration.csv",)),
        Source("canonical", dest / "canonical", ("capture.json",)),
    )}


def mutated_copy(source: Source, dest: Path, seed: int) -> tuple[Path, list[str]]:
    """A copy of `source` at `dest` (images hard-linked: nothing writes them) with one to
    three mutations of its metadata files; returns the folder and what was done."""
    rng = random.Random(seed)
    shutil.copytree(source.root, dest, copy_function=_link)
    done = []
    for _ in range(rng.choice((1, 1, 2, 3))):
        rel = rng.choice(source.files)
        path = dest / rel
        data = path.read_bytes()
        path.unlink()  # a hard link: never write through to the source
        new, what = mutate(rel, data, rng)
        path.write_bytes(new)
        done.append(f"{rel}: {what}")
    return dest, done


def _link(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def mutate(name: str, data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """`data` of the file `name` mutated once: by its form 3 times in 4, else byte damage."""
    if rng.random() < 0.25:
        return _bytes(data, rng)
    kind = Path(name).suffix
    try:
        if kind == ".json":
            return _json(data, rng)
        if kind == ".npz":
            return _npz(data, rng)
        if kind in (".csv", ".txt"):
            return _text(data, rng, "," if kind == ".csv" else " ")
        if kind == ".bin":
            return _binary(data, rng)
    except Exception:  # noqa: BLE001 - an earlier mutation broke the form already
        pass
    return _bytes(data, rng)


def attack(rng: random.Random) -> object:
    """A hostile value, or a random number or string."""
    roll = rng.random()
    if roll < 0.7:
        return rng.choice(ATTACKS)
    if roll < 0.85:
        return rng.choice((rng.uniform(-1e6, 1e6), rng.randint(-(2**40), 2**40)))
    alphabet = "aZ09_.-/\\ ,:\"'#\n\tкⅫ\x00\u202e"
    return "".join(rng.choice(alphabet) for _ in range(rng.randint(1, 12)))


def _bytes(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    buf = bytearray(data)
    roll = rng.random()
    if roll < 0.3 or not buf:
        cut = rng.randint(0, len(buf))
        return bytes(buf[:cut]), f"truncated at {cut}"
    if roll < 0.7:
        for _ in range(rng.randint(1, 8)):
            buf[rng.randrange(len(buf))] = rng.randrange(256)
        return bytes(buf), "bytes flipped"
    at = rng.randint(0, len(buf))
    junk = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
    return bytes(buf[:at] + junk + buf[at:]), f"{len(junk)} bytes inserted at {at}"


def _nodes(tree: object, path: tuple = ()) -> list[tuple]:
    """Every path into a decoded JSON tree (lists sampled: a rig has thousands of numbers)."""
    out = [path]
    if isinstance(tree, dict):
        for key, value in tree.items():
            out += _nodes(value, path + (key,))
    elif isinstance(tree, list):
        for i, value in enumerate(tree[:4]):
            out += _nodes(value, path + (i,))
    return out


def _json(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    tree = json.loads(data)
    path = rng.choice(_nodes(tree))
    if not path:
        tree, what = attack(rng), "replaced whole"
    else:
        parent = tree
        for key in path[:-1]:
            parent = parent[key]
        key, roll = path[-1], rng.random()
        if roll < 0.6:
            parent[key] = value = attack(rng)
            what = f"{list(path)} = {value!r:.60}"
        elif roll < 0.75:
            del parent[key]
            what = f"{list(path)} removed"
        elif roll < 0.9 and isinstance(parent, list):
            parent.insert(key, json.loads(json.dumps(parent[key])))
            what = f"{list(path)} repeated"
        else:
            parent[key] = [parent[key]]
            what = f"{list(path)} wrapped in a list"
    return json.dumps(tree, ensure_ascii=rng.random() < 0.5).encode(), what


def _text(data: bytes, rng: random.Random, sep: str) -> tuple[bytes, str]:
    lines = data.decode("utf-8").split("\n")
    i = rng.randrange(len(lines))
    roll = rng.random()
    if roll < 0.6:
        cells = lines[i].split(sep)
        j = rng.randrange(len(cells))
        value = attack(rng)
        cells[j] = value if isinstance(value, str) else json.dumps(value)
        lines[i] = sep.join(cells)
        what = f"line {i + 1} cell {j} = {cells[j]!r:.60}"
    elif roll < 0.75:
        del lines[i]
        what = f"line {i + 1} removed"
    elif roll < 0.9:
        lines.insert(i, lines[i])
        what = f"line {i + 1} repeated"
    else:
        cells = lines[i].split(sep)
        lines[i] = sep.join(cells[:rng.randint(0, len(cells))])
        what = f"line {i + 1} cut short"
    if sep == "," and rng.random() < 0.2:  # quoting the CSV way
        rows = list(csv.reader(io.StringIO("\n".join(lines))))
        out = io.StringIO()
        csv.writer(out, quoting=csv.QUOTE_ALL).writerows(rows)
        return out.getvalue().encode(), what + ", all quoted"
    return "\n".join(lines).encode("utf-8"), what


_WORDS = (0, 1, 2**31 - 1, 2**31, 2**32 - 1, 2**63, 2**64 - 1, 1000, 10**6)


def _binary(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """A COLMAP record field overwritten: a count, an id, a size or a double."""
    buf = bytearray(data)
    if len(buf) < 8:
        return _bytes(data, rng)
    fields = [at for at in (0, 8, 12, 16, 24) if at + 8 <= len(buf)]
    at = rng.choice(fields) if rng.random() < 0.5 else rng.randrange(len(buf) - 7)
    if rng.random() < 0.5:
        word = rng.choice(_WORDS)
        struct.pack_into("<Q", buf, at, word)
        return bytes(buf), f"uint64 {word} at {at}"
    value = rng.choice((float("nan"), float("inf"), -1e308, 0.0, 1e-320))
    struct.pack_into("<d", buf, at, value)
    return bytes(buf), f"double {value} at {at}"


def _npz(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    key = rng.choice(sorted(arrays))
    roll = rng.random()
    if roll < 0.2:
        del arrays[key]
        what = f"{key} removed"
    elif roll < 0.3:
        arrays[key + "x" if rng.random() < 0.5 else "world_mat_99"] = arrays.pop(key)
        what = f"{key} renamed"
    else:
        arrays[key], what = _array(arrays[key], rng)
        what = f"{key}: {what}"
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue(), what


def _array(arr: np.ndarray, rng: random.Random) -> tuple[np.ndarray, str]:
    options = [
        (lambda: arr.astype(np.float64) * np.nan, "all NaN"),
        (lambda: arr.astype(np.float64) * 1e308, "times 1e308"),
        (lambda: np.zeros_like(arr), "zeros"),
        (lambda: arr.reshape(-1), "flattened"),
        (lambda: arr[:2], "two rows"),
        (lambda: arr[None], "one more axis"),
        (lambda: np.array(5.0), "a scalar"),
        (lambda: np.zeros((0, 4)), "empty"),
        (lambda: np.array(["x"] * arr.size).reshape(arr.shape), "strings"),
        (lambda: arr.astype(np.complex128), "complex"),
        (lambda: arr > 0, "booleans"),
        (lambda: np.full((3, 4), 2**62, np.int64), "huge integers"),
    ]
    make, what = rng.choice(options)
    with np.errstate(all="ignore"):  # 1e308 times a few overflows: that is the point
        return make(), what


READER = {"colmap-text": "colmap", "colmap-binary": "colmap"}
"""The importer of each source kind that is not named as its kind."""


def run_importer(source: Source, folder: Path, out: Path) -> tuple[str, str]:
    """("imported" | "refused" | "unexpected", what) of reading the mutated `folder` with the
    source's reader (canonical: validated): refused means a CaptureError whose every problem
    has a message and names a file of the source; anything else raised is unexpected (`what`:
    its type on the first line, then the traceback)."""
    import traceback

    from core.data import CaptureError, check_capture, import_capture

    try:
        if source.fmt == "canonical":
            check_capture(folder)
        else:
            import_capture(folder, out, READER.get(source.fmt, source.fmt))
    except CaptureError as exc:
        # Absolute paths are the source's or the output's; validation names files relative
        # to the capture.
        bad = [p for p in exc.problems if not p.message or os.path.isabs(p.path) and not (
            p.path.startswith(str(folder)) or p.path.startswith(str(out)))]
        if not exc.problems or bad:
            return "unexpected", f"CaptureError without a message or a file\n{bad}"
        return "refused", str(exc.problems[0])
    except Exception as exc:  # noqa: BLE001 - what the fuzz is looking for
        kind = type(exc)
        name = kind.__name__ if kind.__module__ == "builtins" else \
            f"{kind.__module__}.{kind.__qualname__}"
        return "unexpected", f"{name}\n" + "".join(traceback.format_exception(exc))[-3000:]
    return "imported", ""
