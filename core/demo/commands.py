"""`dgs demo`: the main job on a small built-in capture. With the service extra installed, the
service package takes this command over (`service.demo`: the same job through an embedded
`dgs serve`, registered through the dgs.commands entry point so core never imports the
service); here it runs in this process. `--raster` runs the rasterizer-only demo
(`core.demo.raster`) instead."""

from __future__ import annotations

import argparse

from core.cli import command_help
from core.demo import run_demo, run_raster_demo

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help=command_help("demo"))
    p.add_argument("--out", default="demo", help="demo folder (default ./demo)")
    p.add_argument("--raster", action="store_true",
                   help="only the rasterizer demo (ground-truth splats, no training)")
    p.add_argument("--in-process", action="store_true",
                   help="run the job in this process, not through the HTTP service")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    if args.raster:
        return run_raster_demo(args.out)
    if not args.in_process:
        print("dgs demo: the service extra is not installed, so the job runs in this process "
              "(pip install -e '.[service]' to run it through the HTTP service)", flush=True)
    return run_demo(args.out)


