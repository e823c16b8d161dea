"""The `dgs` command line.

Each command lives beside its code in a ``commands`` module exposing ``register(subparsers)``
(``core/pipeline/commands.py`` is ``dgs reconstruct``, ``core/mesh/commands.py`` ``dgs mesh``,
...); ``COMMANDS`` lists them, and only the module of the command being run is imported, so
``dgs --help`` and ``dgs serve`` load no torch. Packages above core (the service and the workers:
``dgs serve``, ``dgs worker``, ``dgs keys``) add theirs through the ``dgs.commands``
entry-point group, so core never imports them (imports go one way, docs/design.md 2.2).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from importlib.metadata import entry_points

from core.data.capture import CaptureError

__all__ = ["COMMANDS", "build_parser", "command_help", "fail", "main"]

# Core's commands: name -> (module with `register(subparsers)`, one-line help). Only the module
# of the command being run is imported (most of them load torch; `dgs serve` must not).
COMMANDS: dict[str, tuple[str, str]] = {
    "capture": ("core.data.commands", "import and validate captures"),
    "demo": ("core.demo.commands", "run the main job on a small built-in capture"),
    "eval": ("core.evaluation.commands", "score a run's held-out views; writes RUN/eval.json"),
    "export": ("core.export.commands", "a run's frames as PLY, SPZ or a relightable stream"),
    "mesh": ("core.mesh.commands", "meshes of a run's frames (TSDF of the geometry branch)"),
    "reconstruct": ("core.pipeline.commands", "reconstruct a capture into a run directory"),
    "relight": ("core.relight.commands", "relit renders of a run under an environment map"),
    "synth": ("core.synth.commands", "generate a synthetic capture with ground truth"),
}


def command_help(name: str) -> str:
    """The one-line help of core command `name` (its module's parser uses it too)."""
    return COMMANDS[name][1]


def fail(command: str, error: str | Exception) -> int:
    """Print `dgs COMMAND: message` on one line of stderr (a capture's problems, the first
    three, with a pointer to `dgs capture validate`) and return exit status 2."""
    message = str(error)
    if isinstance(error, CaptureError):
        shown = "; ".join(str(p) for p in error.problems[:3])
        more = len(error.problems) - 3
        message = (f"not a valid capture: {shown}" + (f" (+{more} more)" if more > 0 else "")
                   + " (see dgs capture validate)")
    print(f"dgs {command}: {message.replace(chr(10), ' ')}", file=sys.stderr)
    return 2


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The parser for `argv` (default sys.argv[1:]): the chosen core command fully, the
    others by name and help only; the entry points' commands (torch-free) always."""
    parser = argparse.ArgumentParser(
        prog="dgs", description="Relightable volumetric video with disentangled 3D Gaussians."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    args = list(sys.argv[1:] if argv is None else argv)
    chosen = next((a for a in args if not a.startswith("-")), None)
    for name, (module, text) in COMMANDS.items():
        if name == chosen:
            importlib.import_module(module).register(sub)
        else:
            sub.add_parser(name, help=text)
    for entry in sorted(entry_points(group="dgs.commands"), key=lambda e: e.name):
        entry.load().register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("dgs: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
