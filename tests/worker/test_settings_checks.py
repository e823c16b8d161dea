"""`dgs serve` and `dgs worker` refuse to start on settings they cannot work with, with one line
naming the variable and what it expects (issue 42): a broker URL of no supported transport
(a worker used to start anyway and log a traceback every 15 s), a job store or artifact store
URL without a known scheme, a public URL without a scheme (it made relative Location headers).
A URL's password never shows."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from service.settings import ServiceSettings
from worker.settings import WorkerSettings, describe

ROOT = Path(__file__).resolve().parents[2]
BAD = {
    "DGS_BROKER_URL": ("reddis://127.0.0.1:6379/0", "expected a broker URL", "'reddis'"),
    "DGS_DATABASE_URL": ("mysql://dgs:s3cret@db/dgs", "expected a job store URL", "'mysql'"),
    "DGS_STORAGE_URL": ("/srv/dgs/store", "expected an artifact store URL", "no scheme"),
    "DGS_PUBLIC_URL": ("dgs.example.com", "expected the base URL clients reach", "'dgs.exa"),
}


def test_the_known_urls_pass_and_the_rest_are_refused(tmp_path: Path):
    good = {"database_url": ["sqlite:///x.sqlite3", "postgresql+psycopg://dgs@db:5432/dgs",
                             "postgresql://dgs@db/dgs"],
            "broker_url": ["redis://r:6379/0", "rediss://r:6380/0", "sqla+sqlite:///b.sqlite3"],
            "storage_url": ["s3://bucket/prefix", "s3://bucket", "file:///srv/store"]}
    for field, urls in good.items():
        for url in urls:
            assert getattr(WorkerSettings(data_dir=tmp_path, **{field: url}), field) == url
    bad = {"database_url": ["postgres://dgs@db/dgs", "db.sqlite3", "sqlite:x"],
           "broker_url": ["amqp://rabbit//", "memory://", "sqla+mysql://u@h/b", "redis"],
           "storage_url": ["gs://bucket", "s3://", "file://"]}
    for field, urls in bad.items():
        for url in urls:
            with pytest.raises(ValidationError) as info:
                WorkerSettings(data_dir=tmp_path, **{field: url})
            assert describe(info.value).startswith(f"DGS_{field.upper()}: expected"), url
    assert ServiceSettings(data_dir=tmp_path, public_url="https://dgs.example.com/x").public_url
    for url in ("dgs.example.com", "//dgs.example.com", "ftp://dgs.example.com", "https://"):
        with pytest.raises(ValidationError):
            ServiceSettings(data_dir=tmp_path, public_url=url)


@pytest.mark.parametrize(("command", "variable"), [
    (command, variable) for command in ("serve", "worker") for variable in sorted(BAD)
    if (command, variable) != ("worker", "DGS_PUBLIC_URL")])  # the API's setting only
def test_the_commands_refuse_to_start(tmp_path: Path, command: str, variable: str):
    value, expected, shown = BAD[variable]
    env = {k: v for k, v in os.environ.items() if not k.startswith("DGS_")}
    env.update({"DGS_DATA_DIR": str(tmp_path / "data"), variable: value})
    out = subprocess.run([sys.executable, "-m", "core.cli", command], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stderr[-2000:]
    assert out.stderr.startswith(f"dgs {command}: {variable}: {expected}"), out.stderr
    assert shown in out.stderr and "Traceback" not in out.stderr
    assert "s3cret" not in out.stderr and len(out.stderr.splitlines()) == 1
    assert not (tmp_path / "data").exists()  # refused before anything was made
