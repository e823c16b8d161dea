"""A worker's pool processes start clean (issue 42): nothing they inherit can hold a lock.

A pool process forked while another thread of the Celery parent was inside SQLite inherited
SQLite's mutexes held and hung for good (in gc, freeing a connection it inherited). The pool
now starts each process as a fresh interpreter; the reproduction (fork_storm.py) starts
hundreds of them the way the pool does, from a thread of their own while two threads hammer
SQLite, and every one must finish. With the old start method (fork) the same run hangs some
40% of its children (docs/decisions/2026-11-29-pool-processes-start-clean.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from worker.celery_app import make_celery
from worker.settings import WorkerSettings

STORM = Path(__file__).with_name("fork_storm.py")
ROOT = Path(__file__).resolve().parents[2]


def test_the_pool_starts_fresh_interpreters(tmp_path: Path):
    app = make_celery(WorkerSettings(data_dir=tmp_path))
    assert app.conf.worker_pool_start_method == "spawn"


@pytest.mark.timeout(300)
def test_no_pool_process_hangs_while_the_parent_is_inside_sqlite(tmp_path: Path):
    out = subprocess.run([sys.executable, str(STORM), str(tmp_path / "storm.sqlite3"),
                          "--children", "200", "--batch", "10", "--wait", "60"], cwd=ROOT,
                         capture_output=True, text=True, timeout=280)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["hung"] == 0 and result["failed"] == 0, result
    assert result["start"] == "spawn" and result["children"] == 200
