"""The `dgs` command line.

Each command family lives in its own module exposing ``register(subparsers)``; the modules are
listed in ``_COMMAND_MODULES`` and imported only when the command line starts, so ``import core``
stays cheap. Packages above core (the service and the workers: ``dgs serve``, ``dgs worker``,
``dgs keys``) add theirs through the ``dgs.commands`` entry-point group, so core never imports
them (imports go one way, DESIGN.md section 2).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from importlib.metadata import entry_points
from collections.abc import Sequence

__all__ = ["main", "build_parser"]

# Modules that add sub-commands; each has `register(subparsers) -> None`.
_COMMAND_MODULES: tuple[str, ...] = (
    "core.commands_demo",
    "core.commands_export",
    "core.commands_reconstruct",
    "core.commands_relight",
    "core.data.commands",
    "core.synth.commands",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dgs", description="Relightable volumetric video with disentangled 3D Gaussians."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in _COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    for entry in sorted(entry_points(group="dgs.commands"), key=lambda e: e.name):
        entry.load().register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("dgs: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
