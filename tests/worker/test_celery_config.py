"""The Celery settings docs/design.md section 4 asks for, on both brokers."""

from __future__ import annotations

from pathlib import Path

from kombu.transport import sqlalchemy as kombu_sqlalchemy

from worker.celery_app import make_celery
from worker.pipelines import PIPELINES, get_pipeline
from worker.settings import WorkerSettings


def test_reliability_settings(tmp_path: Path):
    app = make_celery(WorkerSettings(data_dir=tmp_path))
    c = app.conf
    assert c.task_acks_late and c.task_reject_on_worker_lost
    assert c.worker_prefetch_multiplier == 1
    # Pool processes are kept between tasks (the next job starts without an interpreter to
    # load), up to a count and a memory cap (KiB), each a setting.
    assert c.worker_max_tasks_per_child == 100 and c.worker_max_memory_per_child == 4096 * 1024
    c = make_celery(WorkerSettings(data_dir=tmp_path, pool_tasks_per_process=1,
                                   pool_process_max_mib=None)).conf
    assert c.worker_max_tasks_per_child == 1 and c.worker_max_memory_per_child is None
    assert c.task_ignore_result and c.accept_content == ["json"]
    assert c.worker_lost_wait == 1.0  # a lost pool process frees its slot in a second, not 10
    assert app.conf.broker_url.startswith("sqlite:///") and str(tmp_path) in c.broker_url
    # Kombu's SQLAlchemy transport, asking an empty queue ten times a second (its default: once)
    with app.connection_for_read() as conn:
        assert isinstance(conn.transport, kombu_sqlalchemy.Transport)
        assert conn.transport.polling_interval == 0.1


def test_redis_visibility_timeout_outlasts_the_longest_job(tmp_path: Path):
    settings = WorkerSettings(data_dir=tmp_path, broker_url="redis://127.0.0.1:6379/0",
                              redis_key_prefix="deploy-a:")
    options = make_celery(settings).conf.broker_transport_options
    for name in PIPELINES:
        soft, hard = get_pipeline(name).limits(settings)
        assert soft < hard < options["visibility_timeout"]
    assert options["global_keyprefix"] == "deploy-a:"


def test_each_pipeline_has_its_own_time_limits(tmp_path: Path):
    settings = WorkerSettings(data_dir=tmp_path, relight_soft_limit_seconds=600,
                              reconstruct_soft_limit_seconds=7200, export_soft_limit_seconds=900,
                              hard_limit_margin_seconds=60)
    assert get_pipeline("relight").limits(settings) == (600, 660)
    assert get_pipeline("reconstruct").limits(settings) == (7200, 7260)
    assert get_pipeline("export").limits(settings) == (900, 960)  # not the relight's
    for name in ("relight", "export"):
        longer = settings.model_copy(update={f"{name}_soft_limit_seconds": 30_000})
        assert longer.visibility_timeout > 30_000 + 60


def test_defaults_live_in_the_data_folder(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("DGS_DATA_DIR", str(tmp_path / "d"))
    monkeypatch.setenv("DGS_RETENTION_DAYS", "")  # empty counts as unset (docker-compose)
    s = WorkerSettings()
    assert s.database == f"sqlite:///{tmp_path / 'd' / 'dgs.sqlite3'}"
    assert s.storage == (tmp_path / "d" / "store").as_uri() and s.embedded_broker
    assert s.scratch == tmp_path / "d" / "work" and s.retention_days is None


def test_a_pool_process_starts_with_every_job_loaded_and_frozen(tmp_path: Path):
    """A pool process, as it starts, imports every pipeline's job and freezes what the imports
    made out of the garbage collector: the full pass after each job then walks only what jobs
    made (it took 0.19 s of each hand-over walking torch's objects). In a process of its own."""
    import json
    import os
    import subprocess
    import sys

    code = ("import gc, json, sys\n"
            "from worker.tasks import _load_the_runner\n"
            "_load_the_runner()\n"
            "print(json.dumps([gc.get_freeze_count(), len(gc.get_objects()),"
            " sorted(m for m in sys.modules if m.endswith('_job'))]))\n")
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("DGS_")},
           "DGS_DATA_DIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).parents[2], env=env,
                         capture_output=True, text=True, check=True).stdout
    frozen, tracked, jobs = json.loads(out.splitlines()[-1])
    assert {f"worker.{p}_job" for p in PIPELINES} <= set(jobs)
    assert frozen > 100_000 and tracked < frozen / 100  # torch's objects among the frozen
