"""The time-limited, carried Panoptic run's helpers (`benchmarks/panoptic.py` on a lent GPU,
`benchmarks/lend.sh`): the seconds kept for the served job, and a previous call's files."""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["resume_files", "serve_reserve"]


def serve_reserve(args, budget) -> float:
    """Seconds to keep for the served job: its frames at the measured rates, 15% for the
    service's own work, a minute to start it and its worker."""
    if not args.serve:
        return 0.0
    from core.config import parse_frames

    n = len(parse_frames(args.serve_frames, [str(i) for i in range(10 ** 4)]))
    keys = -(-n // args.gop)
    key, tracked = budget.predict("key") or 0.0, budget.predict("tracked") or 0.0
    return 1.15 * (keys * key + (n - keys) * tracked) + 60


def resume_files(args, run: Path) -> list[dict]:
    """Lay `--resume-from`'s pack out as OUT/run (unless OUT/run is there); returns the earlier
    call's rows (from its r.tgz's result.json)."""
    import tarfile

    from core.pipeline.carry import unpack_resume

    if args.resume_from is None:
        return []
    if not (run / "config.json").is_file():
        unpack_resume(args.resume_from, run)
    if (args.resume_from / "result.json").is_file():
        return list(json.loads((args.resume_from / "result.json").read_text()).get("rows", []))
    tgz = args.resume_from / "r.tgz"
    if not tgz.is_file():
        return []
    with tarfile.open(tgz) as tar:
        member = next((m for m in tar.getmembers() if m.name.endswith("p/result.json")), None)
        data = tar.extractfile(member) if member is not None and member.isfile() else None
        return list(json.loads(data.read()).get("rows", [])) if data is not None else []
