"""The job store's engine and sessions, and its schema kept by Alembic migrations.

SQLite (the embedded default) is shared by the API process and the worker processes, so it runs
in WAL mode with a busy timeout; foreign keys are switched on so deletes cascade as on
PostgreSQL. Write transactions start with BEGIN IMMEDIATE: in WAL mode a transaction that reads
first and writes later fails at once ("database is locked", no busy wait) when another writer
committed in between; taking the write lock up front makes it wait its turn instead. Read-only
sessions (`session_scope(url, write=False)`) begin deferred and never wait for writers.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.orm import Session, sessionmaker

__all__ = ["MIGRATIONS", "engine_for", "migrate", "session_scope", "sessions_for"]

MIGRATIONS = Path(__file__).resolve().parent / "migrations"


def _sqlite_pragmas(dbapi_connection, _record) -> None:
    dbapi_connection.isolation_level = None  # SQLAlchemy's begin event issues BEGIN itself
    cur = dbapi_connection.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.close()


def _sqlite_begin(conn) -> None:
    read_only = conn.get_execution_options().get("dgs_read_only", False)
    conn.exec_driver_sql("BEGIN" if read_only else "BEGIN IMMEDIATE")


_ENGINES: dict[str, Engine] = {}


_INHERITED: list[object] = []
"""In a forked child: the connection pools inherited from the parent, kept referenced."""


def _forget_parent_connections() -> None:
    """In a child forked by Python code (the workers' pools start fresh interpreters; this is
    for anything else that forks), give each engine a new pool: two processes talking over one
    PostgreSQL connection corrupt each other's transactions (SQLAlchemy's fork recipe). The
    inherited pools stay referenced, never freed: freeing a SQLite connection takes SQLite's
    global mutexes, which another thread of the parent may have held at the fork (the pool
    process that hung in gc, issue 42)."""
    for engine in _ENGINES.values():
        _INHERITED.append(engine.pool)
        engine.dispose(close=False)


os.register_at_fork(after_in_child=_forget_parent_connections)


def engine_for(url: str) -> Engine:
    """One engine per URL per process (connection pools are per process)."""
    engine = _ENGINES.get(url)
    if engine is None:
        engine = _ENGINES[url] = _create(url)
    return engine


def _create(url: str) -> Engine:
    if url.startswith("sqlite"):
        path = url.split("///", 1)[-1]
        if path and path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False})
        event.listen(engine, "connect", _sqlite_pragmas)
        event.listen(engine, "begin", _sqlite_begin)
        return engine
    # A job store that does not answer fails a request within seconds (the API answers 503)
    # instead of holding it until the operating system gives up on the connection.
    args = {"connect_timeout": 10} if url.startswith("postgresql") else {}
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20,
                         connect_args=args)


@functools.lru_cache(maxsize=16)
def sessions_for(url: str, write: bool = True) -> sessionmaker[Session]:
    """Session factory; `write=False` sessions begin deferred on SQLite (reads only)."""
    engine = engine_for(url)
    if not write:
        engine = engine.execution_options(dgs_read_only=True)
    return sessionmaker(engine, expire_on_commit=False)


@contextmanager
def session_scope(url: str, write: bool = True) -> Iterator[Session]:
    """A session that commits on success and rolls back on error."""
    session = sessions_for(url, write)()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def alembic_config(url: str):
    # lazy: only to migrate (alembic is slow to import)
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    cfg.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return cfg


def migrate(url: str) -> None:
    """Bring the job store's schema to the newest migration (idempotent; safe to call at every
    start of the API or a worker)."""
    # lazy: only to migrate
    from alembic import command

    engine = engine_for(url)
    with engine.begin() as connection:
        cfg = alembic_config(url)
        cfg.attributes["connection"] = connection
        command.upgrade(cfg, "head")
