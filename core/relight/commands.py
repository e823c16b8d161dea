"""`dgs relight RUN --envmap FILE --out DIR ...`. Bad input ends with one line on stderr and exit
status 2; no traceback. A progress bar over the views shows on a terminal."""

from __future__ import annotations

import argparse
import sys
import time

from tqdm import tqdm

from core.cli import command_help, fail
from core.relight import parse_light, relight_run

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("relight", help=command_help("relight"))
    p.add_argument("run", help="run directory (of dgs reconstruct)")
    p.add_argument("--envmap", default=None, metavar="FILE",
                   help="equirectangular environment map, .exr or .hdr (width = 2 x height), "
                        "or a built-in one: builtin:studio, builtin:sunset, builtin:neon; "
                        "without one the environment is black and --light must be given")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--rotation", type=float, default=0.0, metavar="DEG",
                   help="turn the map about the capture's up axis (degrees, right-hand rule)")
    p.add_argument("--exposure", type=float, default=0.0, metavar="EV",
                   help="map exposure in stops (radiance x 2**EV)")
    p.add_argument("--light", action="append", default=[], metavar="SPEC",
                   help="add a light: directional:X,Y,Z:INTENSITY[:R,G,B] (X,Y,Z towards it) or "
                        "point:X,Y,Z:INTENSITY[:R,G,B] (its position); repeatable")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="slice of the run's finished frames (default all); with several, "
                        "also OUT/videos/<camera>.mp4 over the frames")
    p.add_argument("--cameras", default="heldout", metavar="WHICH",
                   help="heldout (default), all, or camera ids ID,ID")
    path = p.add_mutually_exclusive_group()
    path.add_argument("--orbit", type=int, default=None, metavar="N",
                      help="render an N-view orbit around the subject and OUT/<frame>.mp4")
    path.add_argument("--camera-path", default=None, metavar="FILE",
                      help="render a nerfstudio camera_path.json and OUT/<frame>.mp4")
    p.add_argument("--fps", type=float, default=24.0, help="MP4 frame rate (default 24)")
    p.add_argument("--capture-light", default=None, metavar="SPEC",
                   help="the capture's own lighting the albedo is divided by: a uniform "
                        "irradiance (default pi), a stage .exr/.hdr map, or a .json with "
                        "sh9_radiance (a dgs synth capture's gt/lights.json)")
    p.add_argument("--no-ao", action="store_true",
                   help="do not shade with the learnt visibility (the no-AO baseline)")
    p.add_argument("--capture", default=None, help="capture folder (default: the run's own)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_relight)


def _relight(args: argparse.Namespace) -> int:
    try:
        lights = [parse_light(s) for s in args.light]
    except ValueError as exc:
        return fail("relight", exc)
    bar = None

    def on_progress(event) -> None:
        nonlocal bar
        if args.no_progress or not sys.stderr.isatty():
            return
        if event.kind == "start":
            bar = tqdm(total=event.total, desc="relight", unit="view", dynamic_ncols=True)
        elif event.kind == "view" and bar is not None:
            bar.set_postfix(frame=event.frame, refresh=False)
            bar.update(1)

    start = time.perf_counter()
    try:
        record = relight_run(args.run, args.out, envmap=args.envmap, rotation_deg=args.rotation,
                             exposure=args.exposure, lights=lights, cameras=args.cameras,
                             frames=args.frames, orbit=args.orbit, camera_path=args.camera_path,
                             capture_dir=args.capture, capture_light=args.capture_light,
                             ao=not args.no_ao, fps=args.fps, on_progress=on_progress)
    except ValueError as exc:
        return fail("relight", str(exc).replace("\n", " "))
    finally:
        if bar is not None:
            bar.close()
    videos = f", {len(record['videos'])} video(s)" if record["videos"] else ""
    print(f"relit {record['views']} view(s) of {len(record['frames'])} frame(s){videos} into "
          f"{args.out} in {time.perf_counter() - start:.1f} s")
    return 0
