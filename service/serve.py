"""`dgs serve`: the API with everything a fresh machine needs (docs/design.md section 4): the job
store migrated, a sweeper thread (re-sends jobs whose worker was lost, deletes what expired),
and, when no broker is configured, one supervised worker subprocess on the embedded SQLite
broker. With DGS_BROKER_URL and DGS_DATABASE_URL set the same command serves a deployment
(workers run elsewhere, `dgs worker`)."""

from __future__ import annotations

import logging
import signal
import sys

import uvicorn

from service.app import create_app
from service.auth import BindRefused, check_bind, has_active_key
from service.settings import ServiceSettings
from worker.db import migrate
from worker.supervise import EmbeddedWorker, make_sweeper, stop_all, worker_env

__all__ = ["serve"]

log = logging.getLogger("dgs.service")


def serve(settings: ServiceSettings, *, worker: bool = True, workers: int = 1) -> int:
    """Run until interrupted; 2 when the bind is refused (see service.auth.check_bind).
    `workers` embedded workers share the machine's cores (`worker.supervise.worker_env`)."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    migrate(settings.database)
    try:
        check_bind(settings.host, settings)
    except BindRefused as exc:
        print(f"dgs serve: {exc}", file=sys.stderr)
        return 2
    app = create_app(settings)
    services = app.state.services

    sweeper = make_sweeper(services.celery, settings, store=services.store,
                           blobs=services.blobs).start()
    embedded = []
    if worker and settings.embedded_broker:
        # worker.log, worker-2.log, ...
        embedded = [EmbeddedWorker(settings, worker_env(settings, i, workers) if workers > 1
                                   else None,
                                   log_name="worker.log" if i == 0 else f"worker-{i + 1}.log"
                                   ).start() for i in range(workers)]
    _announce(settings, len(embedded))
    # Uvicorn shuts down gracefully on SIGTERM, then raises the signal again with the handler
    # it found installed: this one, so the embedded worker is stopped below instead of being
    # left running without its server.
    previous = signal.signal(signal.SIGTERM, _stopped)
    try:
        uvicorn.run(app, host=settings.host, port=settings.port, log_level="info",
                    timeout_graceful_shutdown=10)
    except _Stopped:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        sweeper.stop()
        stop_all(embedded)
    return 0


class _Stopped(Exception):
    pass


def _stopped(signum, frame) -> None:
    raise _Stopped


def _announce(settings: ServiceSettings, worker: int) -> None:
    keys = ("API keys required" if has_active_key(settings.database)
            else "no API keys exist: requests run as tenant 'local' (loopback only)")
    if worker:
        workers = (f"{'one embedded worker' if worker == 1 else f'{worker} embedded workers'} "
                   f"(log: {settings.data_dir / 'logs' / 'worker.log'})")
    elif settings.embedded_broker:
        workers = "no worker (--no-worker): start `dgs worker` with the same DGS_DATA_DIR"
    else:
        workers = f"workers on broker {settings.broker.split('@')[-1]} (`dgs worker`)"
    print(f"dgs serve: http://{settings.host}:{settings.port}  (OpenAPI: /docs)\n"
          f"  data:    {settings.data_dir}\n"
          f"  store:   {settings.database.split('@')[-1]}, artifacts {settings.storage}\n"
          f"  workers: {workers}\n"
          f"  auth:    {keys}", flush=True)
