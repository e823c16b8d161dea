"""`dgs export RUN --format ply|spz|stream[,...] --out DIR`: deliver a run's frames as PLYs,
SPZ files or the relightable sequence stream (core.export.run, docs/stream.md).

Bad input ends with one line on stderr and exit status 2; no traceback.
"""

from __future__ import annotations

import argparse

from core.cli import command_help, fail
from core.export.codec import StreamConfig
from core.export.run import export_run

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help=command_help("export"))
    p.add_argument("run", help="run directory (of dgs reconstruct)")
    p.add_argument("--format", default="stream", metavar="FORMATS",
                   help="comma-separated: ply (the frame PLYs), spz (one SPZ per frame), "
                        "stream (OUT/stream.dgss, the sequence stream the web page plays); "
                        "default stream")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="slice of the run's finished frames (default all)")
    p.add_argument("--fps", type=float, default=None,
                   help="the stream's frame rate (default: capture.json's fps, else 24)")
    p.add_argument("--capture", default=None, metavar="DIR",
                   help="the capture, when it moved since the run (cameras and up axis for "
                        "the stream's header)")
    p.add_argument("--subject", action="store_true",
                   help="only the subject: the Gaussians inside the hull of the capture's "
                        "masks (the performers without the stage)")
    p.add_argument("--position-tolerance", type=float, default=None, metavar="F",
                   help="stream: largest centre error, fraction of a group's bounding-box "
                        "diagonal (default 1e-4)")
    p.set_defaults(func=_export)


def _export(args: argparse.Namespace) -> int:
    try:
        config = StreamConfig() if args.position_tolerance is None else StreamConfig(
            position=args.position_tolerance)
        record = export_run(args.run, args.out, formats=[f.strip() for f in
                                                        args.format.split(",") if f.strip()],
                            frames=args.frames, fps=args.fps, config=config,
                            capture_dir=args.capture, subject=args.subject)
    except ValueError as exc:
        return fail("export", exc)
    ply = record["ply_bytes_per_frame"]
    print(f"{len(record['frames'])} frame(s), PLY {ply / 1e6:.2f} MB a frame")
    if "subject" in record:
        print(f"subject: {record['subject']['gaussians_per_frame']:.0f} Gaussians a frame "
              f"({record['subject']['share']:.1%} of the scene's)")
    for fmt in ("spz", "stream"):
        if fmt in record:
            r = record[fmt]
            print(f"{fmt}: {r['bytes_per_frame'] / 1e3:.1f} kB a frame ({r['ratio_to_ply']:.1f}x "
                  f"smaller than PLY), {r['encode_seconds_per_frame'] * 1e3:.0f} ms a frame")
    print(f"wrote {args.out}/export.json")
    return 0
