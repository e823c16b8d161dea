"""`dgs demo` through the service, with a tiny capture and schedule: an embedded `dgs serve`
subprocess (API + worker), the capture uploaded over HTTP, a real reconstruct job (test preset)
followed to success, its artifacts (the PLY included) downloaded byte-exact, evaluated, the
contact sheet made, the server stopped."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest

from core.cli import build_parser
from core.config import read_run
from service import demo as demo_module
from service.demo import run_service_demo

pytestmark = pytest.mark.timeout(600)
TINY_SYNTH = {"frames": 1, "views": 8, "width": 32, "height": 32, "seed": 3, "priors": False,
              "ao_directions": 8}
TINY_CONFIG = {"train": {"init_points": 500, "schedule": {
    "iterations": 40, "stage2_start": 12, "stage3_start": 28, "densify_from": 2,
    "densify_until": 24, "densify_interval": 4, "reset_interval": 16, "sh_interval": 4}}}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").exists() and "Z" not in (
        Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0])


def test_demo_command_runs_through_the_service():
    args = build_parser(["demo"]).parse_args(["demo"])
    assert args.func.__module__ == "service.commands"
    assert not args.in_process and not args.raster


def test_the_demo_through_the_service(tmp_path, monkeypatch, capsys):
    servers = []
    real = demo_module.DemoServer

    def recording(*a, **kw):
        server = real(*a, **kw)
        servers.append(server)
        return server

    monkeypatch.setattr(demo_module, "DemoServer", recording)
    out = tmp_path / "demo"
    assert run_service_demo(str(out), synth=TINY_SYNTH, overrides=TINY_CONFIG) == 0
    text = capsys.readouterr().out
    run = out / "run"
    ply = run / "frames" / "000000" / "gaussians.ply"
    assert ply.read_bytes().startswith(b"ply\n")
    # What was downloaded is what the worker published (checked by SHA-256 on the way too).
    data = out / "service"
    (stored,) = (data / "store" / "jobs").glob("*/artifacts/frames/000000/gaussians.ply")
    assert stored.read_bytes() == ply.read_bytes()
    assert (run / "contact_sheet.png").is_file()
    assert (run / "renders" / "000000" / "cam00_rgb.png").is_file()
    result = json.loads((run / "eval.json").read_text())  # evaluated here, after the download
    assert [f["frame"] for f in result["per_frame"]] == ["000000"]
    assert math.isfinite(result["psnr"]) and -1 <= result["normal_cos"] <= 1
    assert read_run(run).config.train.schedule.iterations == 40
    assert "[6/6] results" in text and "contact sheet:" in text and "%" in text
    assert "smaller than the PLY" in text and "open it in a browser:" in text
    assert (run / "export" / "stream.dgss").read_bytes().startswith(b"DGSS")
    # The server and its worker are gone.
    (server,) = servers
    assert server.proc.returncode == 0
    assert not _alive(server.proc.pid)
