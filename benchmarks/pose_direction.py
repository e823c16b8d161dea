"""How far apart correct and inverted poses are by `core.data.importers.rig.shared_view`: the
measurement behind the direction rule's thresholds (docs/decisions/2026-11-29-mirrored-and-
inverted-poses.md).

    .venv/bin/python benchmarks/pose_direction.py [--trials 20] [--data ../shared/data]

For each kind of rig (the `dgs synth` dome at 2..64 cameras, a turntable ring, an arc of a
hand-held capture, forward-facing grids aimed at a point or parallel, and an outward-looking
rig whose cameras share nothing), in `--trials` worlds each (a random rotation, a translation
from 0 to 10 times the rig's size, a scale from 0.01 to 100), it prints the fraction of cameras
that share a view as given and with every pose inverted, over all trials (min..max), and how
often the rule refuses the correct poses and the inverted ones. The real captures of `--data`
(the instant-ngp fox, the Panoptic basketball) are read as their importers read them.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.data.capture import Camera  # noqa: E402
from core.data.importers.common import OPENGL_TO_OPENCV  # noqa: E402
from core.data.importers.direction import looks_inverted, other_way, shared_view  # noqa: E402
from core.synth.generate import SynthConfig, dome_cameras, look_at  # noqa: E402

_K = np.array([[60.0, 0, 32], [0, 60.0, 32], [0, 0, 1]])  # 56 degrees across 64 pixels


def _camera(i: int, w2c: np.ndarray, K: np.ndarray = _K) -> Camera:
    return Camera(f"c{i:03d}", 64, 64, K, w2c)


def _jitter(w2c: np.ndarray, rng: np.random.Generator, degrees: float) -> np.ndarray:
    axis = rng.normal(size=3)
    angle = np.radians(rng.normal(0, degrees))
    k = axis / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    out = w2c.copy()
    out[:3, :3] = (np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx) @ w2c[:3, :3]
    return out


def _ring(n: int, rng, elev: float = 15.0, arc: float = 360.0, outward: bool = False):
    cams = []
    for i in range(n):
        az = np.radians(arc * i / (n if arc == 360 else max(n - 1, 1)))
        eye = 3.0 * np.array([np.cos(az) * np.cos(np.radians(elev)),
                              np.sin(az) * np.cos(np.radians(elev)), np.sin(np.radians(elev))])
        target = 2 * eye if outward else np.zeros(3)
        cams.append(_camera(i, _jitter(look_at(eye, target, (0, 0, 1)), rng, 2.0)))
    return cams


def _grid(n: int, rng, depth: float, aimed: bool):
    side = int(np.ceil(np.sqrt(n)))
    cams = []
    for i in range(n):
        eye = np.array([(i % side) - (side - 1) / 2, (i // side) - (side - 1) / 2, 0.0]) * 0.2
        target = np.array([0, 0, depth]) if aimed else eye + [0, 0, depth]
        cams.append(_camera(i, _jitter(look_at(eye, target, (0, -1, 0)), rng, 1.0)))
    return cams


def _room(n: int, rng, height: float):
    """A hand-held scan of a room from its middle: upright cameras (z up), looking out all
    round, pitched up to 20 degrees, within half a metre of a point `height` above the
    world's origin."""
    cams = []
    for i in range(n):
        eye = np.array([*rng.uniform(-0.5, 0.5, 2), height + rng.uniform(-0.2, 0.2)])
        az, pitch = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(-20, 20))
        look = [np.cos(az) * np.cos(pitch), np.sin(az) * np.cos(pitch), np.sin(pitch)]
        cams.append(_camera(i, _jitter(look_at(eye, eye + look, (0, 0, 1)), rng, 3.0)))
    return cams


def _huddle(n: int, rng, pitch: float, height: float):
    """Cameras within 2 cm of a point `height` above the origin, turned all round and pitched
    up to `pitch` degrees: a panorama from a tripod (no baseline)."""
    cams = []
    for i in range(n):
        eye = np.array([0, 0, height]) + rng.uniform(-0.02, 0.02, 3)
        az, up = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(-pitch, pitch))
        look = [np.cos(az) * np.cos(up), np.sin(az) * np.cos(up), np.sin(up)]
        cams.append(_camera(i, look_at(eye, eye + look, (0, 0, 1))))
    return cams


def _rolled(n: int, rng):
    """A hand-held orbit of 120 degrees whose camera turns about its axis at random (roll up
    to 90 degrees either way: portrait and landscape)."""
    cams = _ring(n, rng, elev=20, arc=120)
    out = []
    for c in cams:
        a = rng.uniform(-np.pi / 2, np.pi / 2)
        roll = np.eye(4)
        roll[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        out.append(replace(c, world_to_camera=roll @ c.world_to_camera))
    return out


def _survey(n: int, rng):
    """A drone's survey: cameras looking straight down from 50 m, in strips flown back and
    forth (every other strip turned 180 degrees)."""
    cams = []
    for i in range(n):
        strip, k = divmod(i, 6)
        eye = np.array([k * 8.0 if strip % 2 == 0 else (5 - k) * 8.0, strip * 10.0, 50.0])
        heading = (0, 1, 0) if strip % 2 == 0 else (0, -1, 0)
        cams.append(_camera(i, _jitter(look_at(eye, eye - [0, 0, 1], heading), rng, 2.0)))
    return cams


def _dome(n: int, rng):
    seed = int(rng.integers(1 << 30))
    return dome_cameras(SynthConfig(views=n, width=64, height=64, seed=seed),
                        np.random.default_rng(seed))


RIGS = {
    **{f"synth dome, {n} cameras": (lambda n: lambda rng: _dome(n, rng))(n)
       for n in (3, 4, 8, 64)},
    "turntable ring, 24": lambda rng: _ring(24, rng),
    "hand-held arc of 90 degrees, 30": lambda rng: _ring(30, rng, elev=25, arc=90),
    "hand-held arc of 45 degrees, 12": lambda rng: _ring(12, rng, elev=10, arc=45),
    "forward-facing grid aimed at 3 m, 20": lambda rng: _grid(20, rng, 3.0, True),
    "forward-facing grid, parallel, 20": lambda rng: _grid(20, rng, 5.0, False),
    "forward-facing grid aimed 500x its spacing away, 20": lambda rng: _grid(20, rng, 100.0, True),
    "orbit of 120 degrees, rolled up to 90 degrees, 24": lambda rng: _rolled(24, rng),
    "drone survey looking down, strips both ways, 36": lambda rng: _survey(36, rng),
    "outward-looking ring, 12": lambda rng: _ring(12, rng, elev=0, outward=True),
    "room scanned from its middle, 40": lambda rng: _room(40, rng, 0.0),
    "room scanned from its middle, origin on the floor, 40": lambda rng: _room(40, rng, 1.6),
    "panorama from a tripod, pitched 60 degrees, 30": lambda rng: _huddle(30, rng, 60, 1.6),
}


def moved(cams: list[Camera], rng: np.random.Generator, upright: str = "") -> list[Camera]:
    """The same rig in another world: rotated (about its up only when `upright` is "z", as z-up
    formats keep it; "-y": up turned to -y, as OpenCV-minded rigs have it), translated (0, 1 or
    10 times its size) and scaled (0.01..100)."""
    if upright:
        a = rng.uniform(0, 2 * np.pi)
        q = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        if upright == "-y":  # z (up) to -y, x stays
            q = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]) @ q
    else:
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))
        q = q if np.linalg.det(q) > 0 else -q
    centres = np.stack([c.center for c in cams])
    size = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) or 1.0
    shift = rng.normal(size=3) * size * rng.choice([0.0, 1.0, 10.0])
    scale = 10.0 ** rng.uniform(-2, 2)
    T = np.eye(4)  # new world from old: X' = scale * (q X + shift)
    T[:3, :3], T[:3, 3] = q, shift
    out = []
    for c in cams:
        w2c = c.world_to_camera @ np.linalg.inv(T)
        w2c[:3, 3] *= scale
        out.append(replace(c, world_to_camera=w2c))
    return out


def _range(values) -> str:
    return f"{min(values):.2f}..{max(values):.2f}" if len(values) else "-"


def row(name: str, trials: list[list[Camera]], up=None) -> str:
    """Over the worlds (min..max): the correct poses' shared view, axis spread and agreement on
    up, the same of the other reading (a field that holds world-to-camera), and how often the
    rule refuses the correct poses and the inverted ones (read as such a field and as
    transforms.json's OpenGL camera-to-world: twice a world). `up`: the world's up where the
    format fixes it."""
    cells = {k: [] for k in ("given", "spread", "up", "other", "ospread", "oup")}
    wrong = caught = 0
    for cams in trials:
        given = shared_view(cams, up)
        cells["given"].append(given.seen / given.counted)
        cells["spread"].append(given.spread)
        cells["up"].append(given.upright)
        for axes in (np.eye(4), OPENGL_TO_OPENCV):
            other = shared_view(other_way(cams, axes), up)
            if axes is not OPENGL_TO_OPENCV:
                cells["other"].append(other.seen / other.counted)
                cells["ospread"].append(other.spread)
                cells["oup"].append(other.upright)
            wrong += looks_inverted(given, other)
            caught += looks_inverted(other, given)
    degrees = {k: f"{min(cells[k]):.0f}..{max(cells[k]):.0f}" for k in ("spread", "ospread")}
    return (f"| {name} | {len(trials[0])} | {_range(cells['given'])} | {degrees['spread']} | "
            f"{_range(cells['up'])} | {_range(cells['other'])} | {degrees['ospread']} | "
            f"{_range(cells['oup'])} | {wrong} | {caught} of {2 * len(trials)} |")


def real(data: Path) -> dict[str, tuple[list[Camera], tuple | None]]:
    """The shared real captures as their importers read them, with the up their format fixes."""
    from core.data.importers.panoptic import read_panoptic
    from core.data.importers.transforms import read_transforms

    out = {}
    if (data / "fox" / "transforms.json").is_file():
        out["fox (real, instant-ngp)"] = (read_transforms(data / "fox").cameras, (0.0, 0.0, 1.0))
    if (data / "panoptic_basketball" / "train_meta.json").is_file():
        out["Panoptic basketball (real)"] = (
            read_panoptic(data / "panoptic_basketball").cameras, None)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print("| rig (worlds) | cameras | shared | axes apart (deg) | agree on up | inverted: "
          "shared | axes apart | agree on up | correct refused | inverted refused |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for kind, upright, up in (("any world", "", None), ("y-down world", "-y", None),
                              ("z-up world", "z", None),
                              ("z-up world, declared", "z", (0.0, 0.0, 1.0))):
        for name, make in RIGS.items():
            trials = [moved(make(rng), rng, upright) for _ in range(args.trials)]
            print(row(f"{name} ({kind})", trials, up), flush=True)
    for name, (cams, up) in real(args.data).items():
        print(row(f"{name} (as shipped)", [cams], up), flush=True)
        trials = [moved(cams, rng) for _ in range(args.trials)]
        print(row(f"{name} (any world)", trials), flush=True)


if __name__ == "__main__":
    main()
