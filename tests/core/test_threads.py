"""OpenMP's wait policy: `core` makes idle threads sleep unless the user chose (docs/design.md
5.12), before torch loads its OpenMP runtime."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PROBE = "import os, core, torch; print(os.environ.get('OMP_WAIT_POLICY'))"


def _policy(value: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if value is not None:
        env["OMP_WAIT_POLICY"] = value
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, env=env, check=True,
                         capture_output=True, text=True)
    return out.stdout.strip()


def test_core_sets_a_passive_wait_before_torch_loads():
    assert _policy(None) == "PASSIVE"


def test_a_policy_the_user_set_is_kept():
    assert _policy("ACTIVE") == "ACTIVE"


def test_every_entry_that_loads_torch_imports_core_first():
    """The policy is read when torch loads OpenMP: each process's entry module must import
    `core` before torch (sys.modules keeps the order imports began)."""
    probe = ("import importlib, sys; importlib.import_module(sys.argv[1]); m = list(sys.modules); "
             "print(m.index('core') < m.index('torch') if 'torch' in m else True)")
    for entry in ("core.cli", "core.pipeline", "worker.runner", "worker.tasks"):
        out = subprocess.run([sys.executable, "-c", probe, entry], cwd=ROOT, check=True,
                             capture_output=True, text=True)
        assert out.stdout.strip() == "True", entry
