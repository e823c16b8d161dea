"""`dgs mesh RUN [--out DIR] ...`: meshes of a run's frames. Bad input ends with one line on
stderr and exit status 2; no traceback. A progress bar over the frames shows on a terminal."""

from __future__ import annotations

import argparse
import sys
import time

from tqdm import tqdm

from core.cli import command_help, fail
from core.config import MeshConfig, validate
from core.mesh import mesh_run

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    m = sub.add_parser("mesh", help=command_help("mesh"))
    m.add_argument("run", help="run directory (of dgs reconstruct)")
    m.add_argument("--out", default=None, help="output folder (default RUN/meshes)")
    m.add_argument("--frames", default=None, metavar="A:B",
                   help="slice of the run's finished frames (default all)")
    m.add_argument("--formats", default="ply", metavar="F,F",
                   help="any of ply, obj, glb, comma-separated (default ply)")
    m.add_argument("--resolution", type=int, default=512, metavar="N",
                   help="voxels along the scene diagonal (default 512)")
    m.add_argument("--depth", default="geometry", choices=("geometry", "appearance"),
                   help="which branch's depth to fuse (appearance: the baseline)")
    m.add_argument("--no-colors", action="store_true", help="no vertex colours")
    m.add_argument("--subject", action="store_true",
                   help="only the subject: the Gaussians inside the hull of the capture's masks")
    m.add_argument("--device", default=None, help="torch device of the TSDF (default: cuda if "
                                                  "available, else cpu)")
    m.add_argument("--capture", default=None, help="capture folder (default: the run's own)")
    m.add_argument("--no-progress", action="store_true", help="no progress bar")
    m.set_defaults(func=_mesh)




def _mesh(args: argparse.Namespace) -> int:
    try:
        config = validate(MeshConfig, {
            "resolution": args.resolution, "depth": args.depth, "colors": not args.no_colors,
            "device": args.device, "subject": args.subject,
            "formats": [f.strip() for f in args.formats.split(",") if f.strip()]})
    except ValueError as exc:
        return fail("mesh", exc)
    bar = None
    show = not args.no_progress and sys.stderr.isatty()

    def on_start(frames: list[str]) -> None:
        nonlocal bar
        if show:
            bar = tqdm(total=len(frames), desc="mesh", unit="frame", dynamic_ncols=True)

    def on_frame(frame: str, info: dict) -> None:
        if bar is not None:
            bar.set_postfix(frame=frame, faces=info.get("faces"), refresh=False)
            bar.update(1)

    start = time.perf_counter()
    try:
        result = mesh_run(args.run, args.out, frames=args.frames, config=config,
                          capture_dir=args.capture, on_start=on_start, on_frame=on_frame)
    except ValueError as exc:
        return fail("mesh", str(exc).replace("\n", " "))
    finally:
        if bar is not None:
            bar.close()
    faces = sum(f.get("faces", 0) for f in result["frames"].values())
    print(f"meshed {len(result['frames'])} frame(s) ({faces} faces) into {result['out']} in "
          f"{time.perf_counter() - start:.1f} s")
    return 0
