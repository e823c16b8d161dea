"""The `dgs` command line.

Each command lives beside its code in a ``commands`` module exposing ``register(subparsers)``
(``core/pipeline/commands.py`` is ``dgs reconstruct``, ``core/mesh/commands.py`` ``dgs mesh``,
...); the modules are listed in ``_COMMAND_MODULES`` and imported only when the command line
starts, so ``import core`` stays cheap. Packages above core (the service and the workers:
``dgs serve``, ``dgs worker``, ``dgs keys``) add theirs through the ``dgs.commands``
entry-point group, so core never imports them (imports go one way, docs/design.md 2.2).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from importlib.metadata import entry_points

__all__ = ["build_parser", "fail", "main"]

# Modules that add sub-commands; each has `register(subparsers) -> None`.
_COMMAND_MODULES: tuple[str, ...] = (
    "core.data.commands",
    "core.demo.commands",
    "core.evaluation.commands",
    "core.mesh.commands",
    "core.pipeline.commands",
    "core.relight.commands",
    "core.synth.commands",
)


def fail(command: str, error: str | Exception) -> int:
    """Print `dgs COMMAND: message` on one line of stderr (a capture's problems, the first
    three, with a pointer to `dgs capture validate`) and return exit status 2."""
    from core.data.capture import CaptureError  # lazy: `dgs --help` needs no capture reader

    message = str(error)
    if isinstance(error, CaptureError):
        shown = "; ".join(str(p) for p in error.problems[:3])
        more = len(error.problems) - 3
        message = (f"not a valid capture: {shown}" + (f" (+{more} more)" if more > 0 else "")
                   + " (see dgs capture validate)")
    print(f"dgs {command}: {message.replace(chr(10), ' ')}", file=sys.stderr)
    return 2


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
