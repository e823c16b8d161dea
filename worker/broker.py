"""Which jobs the broker still holds a message for, so that the sweeper re-sends a queued job
only when its message is really gone (a worker died holding it, Redis lost its data, a queue
was purged), not merely because it waited long.

A job's message is held while it waits in the queue, or was delivered to a worker less than
`grace` seconds ago (that worker claims the job at once; a delivered message whose job is
still queued `grace` seconds later belongs to a worker that died). For the two brokers the
project supports:

- Redis (kombu's transport): waiting messages are the queue's lists (one per priority step);
  delivered, unacknowledged ones are the `unacked` hash, with their delivery time in the
  `unacked_index` sorted set.
- The embedded SQLAlchemy transport (kombu_queue / kombu_message tables): a waiting message is
  a visible row; delivery hides it and stamps its `timestamp` (kombu never deletes it).

Any other broker cannot be inspected: `held_jobs` answers None and the sweeper falls back to
the age rule (DGS_REQUEUE_AFTER_SECONDS).
"""

from __future__ import annotations

import base64
import datetime as dt
import json
import time
from collections.abc import Iterable
from typing import Any

import sqlalchemy as sa
from celery import Celery
from sqlalchemy.exc import OperationalError, ProgrammingError

from worker.celery_app import TASK_NAME
from worker.settings import WorkerSettings

__all__ = ["BrokerInspector", "job_of_message"]


def job_of_message(message: Any) -> str | None:
    """The job id a kombu message (the dict a transport stores) carries to dgs.run_job."""
    try:
        if isinstance(message, (str, bytes)):
            message = json.loads(message)
        if (message.get("headers") or {}).get("task") != TASK_NAME:
            return None
        body = message["body"]
        if (message.get("properties") or {}).get("body_encoding") == "base64":
            body = base64.b64decode(body)
        args = json.loads(body)[0]
        return args[0] if args and isinstance(args[0], str) else None
    except (ValueError, KeyError, IndexError, TypeError, AttributeError):
        return None


class BrokerInspector:
    """`held_jobs(grace)`: ids of the jobs with a message held by the broker (see the module's
    docstring), or None when this broker cannot be inspected."""

    def __init__(self, app: Celery, settings: WorkerSettings):
        self.app, self.settings = app, settings
        self._engine = None

    def held_jobs(self, grace: float) -> set[str] | None:
        broker = self.settings.broker
        if broker.startswith(("redis://", "rediss://")):
            return self._redis(grace)
        if broker.startswith("sqla+"):
            return self._sqla(broker.removeprefix("sqla+"), grace)
        return None

    def _redis(self, grace: float) -> set[str]:
        queue = self.settings.queue
        with self.app.connection_for_read() as conn:
            channel = conn.default_channel
            client = channel.client  # prefixes the keys of the commands kombu itself uses
            prefix = "" if "LRANGE" in getattr(client, "PREFIXED_SIMPLE_COMMANDS", ()) else \
                channel.global_keyprefix
            waiting: list[bytes] = []
            for pri in channel.priority_steps:
                waiting += client.lrange(prefix + channel._q_for_pri(queue, pri), 0, -1)
            since = time.time() - grace
            recent = {tag for tag, at in client.zrange(channel.unacked_index_key, 0, -1,
                                                       withscores=True) if at >= since}
            delivered = [client.hget(channel.unacked_key, tag) for tag in recent]
        jobs = _ids(waiting)
        for raw in delivered:  # [message, exchange, routing key]; the hash serves every queue
            try:
                message, _, routing_key = json.loads(raw) if raw else (None, None, None)
            except (ValueError, TypeError):
                continue
            if routing_key == queue:
                jobs |= _ids([message])
        return jobs

    def _sqla(self, url: str, grace: float) -> set[str]:
        if self._engine is None:
            args = {"timeout": 30} if url.startswith("sqlite") else {}
            self._engine = sa.create_engine(url, connect_args=args)
        # kombu stamps a delivery with datetime.now(): naive local time.
        since = dt.datetime.now() - dt.timedelta(seconds=grace)
        queues = sa.table("kombu_queue", sa.column("id"), sa.column("name"))
        messages = sa.table("kombu_message", sa.column("queue_id"),
                            sa.column("visible", sa.Boolean),
                            sa.column("timestamp", sa.DateTime), sa.column("payload"))
        query = (sa.select(messages.c.payload)
                 .join(queues, queues.c.id == messages.c.queue_id)
                 .where(queues.c.name == self.settings.queue,
                        (messages.c.visible == sa.true()) | (messages.c.timestamp >= since)))
        try:
            with self._engine.connect() as conn:
                payloads = list(conn.execute(query).scalars())
        except (OperationalError, ProgrammingError) as exc:
            if "no such table" in str(exc) or "does not exist" in str(exc):
                return set()  # nothing was ever sent through this broker
            raise
        return _ids(payloads)


def _ids(raw_messages: Iterable[Any]) -> set[str]:
    return {job for job in map(job_of_message, raw_messages) if job is not None}
