"""`dgs capture import` and `dgs capture validate`."""

from __future__ import annotations

import argparse
import os
import sys

from core.cli import command_help
from core.data.capture import CaptureError
from core.data.importers import FORMATS, import_capture
from core.data.schema import load_capture
from core.data.validate import validate_capture

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("capture", help=command_help("capture"))
    csub = p.add_subparsers(dest="capture_command", metavar="SUBCOMMAND")
    csub.required = True

    imp = csub.add_parser(
        "import", help="convert a capture from another format into the canonical layout"
    )
    imp.add_argument("src", help="source folder (or transforms.json / calibration.csv / cameras.npz)")
    imp.add_argument("--out", required=True, help="new capture folder (must not exist or be empty)")
    imp.add_argument(
        "--format", default="auto", choices=["auto", *FORMATS]
    )
    imp.add_argument(
        "--link",
        action="store_true",
        help="hard-link images instead of copying when possible (saves space; the files are then "
        "shared with the source, so never edit them in place)",
    )
    imp.set_defaults(func=_import)

    val = csub.add_parser("validate", help="check a capture; lists every problem, changes nothing")
    val.add_argument("capture", help="capture folder")
    val.set_defaults(func=_validate)


def _import(args: argparse.Namespace) -> int:
    try:
        capture = import_capture(args.src, args.out, args.format, link=args.link)
    except CaptureError as exc:
        _print_problems(f"import of {args.src} failed", exc.problems)
        return 1
    print(
        f"imported {len(capture.cameras)} cameras x {len(capture.frames)} frames "
        f"({capture.import_record['format']}) into {args.out}"
    )
    for warning in capture.import_record.get("warnings", []):  # e.g. a mirrored world undone
        print(f"dgs: warning: {warning}", file=sys.stderr)
    return 0


def _validate(args: argparse.Namespace) -> int:
    problems = validate_capture(args.capture)
    if problems:
        _print_problems(f"{args.capture} is not a valid capture", problems, args.capture)
        return 1
    capture = load_capture(args.capture)
    print(f"{args.capture}: valid ({len(capture.cameras)} cameras x {len(capture.frames)} frames)")
    return 0


def _print_problems(title: str, problems: list, root: str = "") -> None:
    """Each problem with its file; validation names files inside the capture relatively, so
    they are shown under `root`."""
    print(f"dgs: {title}: {len(problems)} problem(s)", file=sys.stderr)
    for p in problems:
        print(f"  {os.path.join(root, p.path)}: {p.message}", file=sys.stderr)
