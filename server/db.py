"""Database plumbing: engines (SQLite in WAL mode or any SQLAlchemy URL), sessions, migrations.

SQLite gets ``foreign_keys=ON``, WAL journaling and a busy timeout on every connection. Its
transactions are begun by us: write sessions say ``BEGIN IMMEDIATE`` so that two writers queue
for the lock up front instead of failing when a read transaction tries to upgrade, and the
writers of one process queue on a lock first (see ``_SqliteWriters``).
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated, Any

from alembic import command
from alembic.config import Config
from fastapi import Depends, Request
from sqlalchemy import Connection, Engine, create_engine, event
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session, sessionmaker

MIGRATIONS_DIR = Path(__file__).parent / "migrations"
_WRITE_OPTION = "srd_write"
SQLITE_BUSY_TIMEOUT_MS = 30_000  # a writer waits this long for the lock before giving up
LOCK_RETRY_S = 0.0005  # how often a writer retries BEGIN IMMEDIATE while another process writes


def is_sqlite(url: str) -> bool:
    """True for ``sqlite:`` URLs."""
    return url.startswith("sqlite")


def _sqlite_on_connect(dbapi_connection: Any, _record: Any) -> None:
    dbapi_connection.isolation_level = None  # we emit BEGIN ourselves (_SqliteWriters.on_begin)
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=NORMAL")  # durable across process crashes in WAL mode
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    cursor.close()


def _begin_immediate(raw: Any) -> None:
    """``BEGIN IMMEDIATE`` on a sqlite3 connection, retried every ``LOCK_RETRY_S`` while
    another process holds the write lock (up to the busy timeout).

    SQLite's own busy handler sleeps 1, 2, 5, 10 ... then 100 ms at a time, so a writer that
    meets a worker's short transaction could sleep far longer than the lock is held; polling
    at half a millisecond keeps that wait close to the holder's transaction time.
    """
    deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_MS / 1000
    raw.execute("PRAGMA busy_timeout=0")
    try:
        while True:
            try:
                raw.execute("BEGIN IMMEDIATE")
                return
            except sqlite3.OperationalError as exc:
                if not _is_busy(exc) or time.monotonic() > deadline:
                    raise
            time.sleep(LOCK_RETRY_S)
    finally:
        raw.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")


def _is_busy(exc: sqlite3.OperationalError) -> bool:
    code = getattr(exc, "sqlite_errorcode", None)
    if isinstance(code, int):
        return code & 0xFF == sqlite3.SQLITE_BUSY
    return "locked" in str(exc) or "busy" in str(exc)


class _SqliteWriters:
    """Queues this process's SQLite writers on a lock instead of in SQLite's busy handler.

    SQLite's busy handler sleeps in growing steps (up to 100 ms) while it waits for the write
    lock, so many threads writing at once would mostly sleep. Here a write transaction takes a
    process-wide lock just before ``BEGIN IMMEDIATE`` and gives it back when its connection
    returns to the pool (after COMMIT or ROLLBACK). Against other processes (the workers) it
    polls SQLite's lock (``_begin_immediate``); they write briefly and rarely.
    """

    _HELD = "srd_write_lock"

    def __init__(self) -> None:
        self._lock = threading.Lock()

    def on_begin(self, connection: Connection) -> None:
        if not connection.get_execution_options().get(_WRITE_OPTION, False):
            connection.exec_driver_sql("BEGIN")
            return
        self._lock.acquire()
        connection.info[self._HELD] = True
        try:
            _begin_immediate(connection.connection.driver_connection)
        except sqlite3.OperationalError as exc:  # as SQLAlchemy reports any statement's failure
            self.release(connection.info)
            raise OperationalError("BEGIN IMMEDIATE", None, exc) from exc
        except BaseException:
            self.release(connection.info)
            raise

    def on_checkin(self, _dbapi_connection: Any, record: Any) -> None:
        self.release(record.info)

    def release(self, info: dict[Any, Any]) -> None:
        if info.pop(self._HELD, False):
            self._lock.release()


def make_engine(url: str) -> Engine:
    """An engine for ``url`` with this project's per-connection settings."""
    if is_sqlite(url):
        engine = create_engine(
            url, connect_args={"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT_MS / 1000}
        )
        writers = _SqliteWriters()
        event.listen(engine, "connect", _sqlite_on_connect)
        event.listen(engine, "begin", writers.on_begin)
        event.listen(engine.pool, "checkin", writers.on_checkin)
        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)


class Database:
    """One engine and its two session factories (read and write)."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.engine = make_engine(url)
        self._read = sessionmaker(bind=self.engine, expire_on_commit=False)
        self._write = sessionmaker(
            bind=self.engine.execution_options(**{_WRITE_OPTION: True}), expire_on_commit=False
        )

    def session(self, *, write: bool) -> Session:
        """A new session; ``write=True`` takes the write lock at BEGIN on SQLite."""
        return self._write() if write else self._read()

    def close(self) -> None:
        """Release every pooled connection."""
        self.engine.dispose()


def alembic_config(url: str) -> Config:
    """The Alembic configuration, built in code (no ini file needed)."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return config


def upgrade_schema(url: str) -> None:
    """Bring the database at ``url`` to the newest schema (``alembic upgrade head``)."""
    command.upgrade(alembic_config(url), "head")


_WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})


async def get_db(request: Request) -> AsyncIterator[Session]:
    """Request-scoped session: one transaction per request, committed by the route.

    The session is made and closed on the event loop (no I/O until the first query; closing
    rolls back a finished read, a sub-millisecond local call), so a request costs one hop to
    the thread pool: the route's own, where every query runs.
    """
    database: Database = request.app.state.database
    session = database.session(write=request.method in _WRITE_METHODS)
    try:
        yield session
    finally:
        session.close()


SessionDep = Annotated[Session, Depends(get_db)]
