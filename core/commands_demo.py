"""`dgs demo`: the main job on the embedded default (what `make demo` runs)."""

from __future__ import annotations

import argparse

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the main job on a small built-in capture")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    # The reconstruction pipeline lands with the static reconstruction issue; until then the demo
    # exercises what exists: the native rasterizer, on a small random scene.
    from core.demo_raster import run_raster_demo

    return run_raster_demo()
