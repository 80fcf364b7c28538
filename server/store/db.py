"""Database plumbing: engines (SQLite in WAL mode or any SQLAlchemy URL), sessions, migrations.

SQLite gets ``foreign_keys=ON``, WAL journaling and a busy timeout on every connection. Its
transactions are begun by us: write sessions say ``BEGIN IMMEDIATE`` so that two writers queue
for the lock up front instead of failing when a read transaction tries to upgrade, and the
writers of one process queue on a lock first (see ``_SqliteWriters``).

A database is never created behind the operator's back: only ``upgrade_schema`` (at a server's
first start on it) may create a SQLite file; every other connection opens it read-write only,
so a deleted file is an error, not a new empty database. ``Database`` remembers what it opened
(the SQLite file's inode, the PostgreSQL database's oid) and ``Database.problem`` notices when
that database is gone or replaced (for good: sessions then refuse to start until a restart), or
on PostgreSQL migrated by a newer release (for good too: an old replica left running through an
upgrade stops taking work), or unreachable (for a while: sessions refuse until a check finds it
back; the pool's pre-ping replaces the connections the outage broke).
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import json
import logging
import math
import os
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeoutError
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import quote

from alembic import command
from alembic.config import Config
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, Engine, create_engine, event, inspect, make_url, text
from sqlalchemy.exc import DBAPIError, InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from sqlalchemy.orm import Session, sessionmaker

log = logging.getLogger("srd.db")
T = TypeVar("T")

MIGRATIONS_DIR = Path(__file__).parent / "migrations"
_WRITE_OPTION = "srd_write"
SQLITE_BUSY_TIMEOUT_MS = 30_000  # a writer waits this long for the lock before giving up
LOCK_RETRY_S = 0.0005  # how often a writer retries BEGIN IMMEDIATE while another process writes
SQLITE_POOL_SIZE = 15
"""SQLite connections a process keeps open: all it may use at once (SQLAlchemy's default 5 kept
plus 10 overflow), so that a burst of requests does not open and close connections, each open
running the PRAGMAs and reading the schema again."""


IDENTITY_CHECK_S = 1.0  # how long a database check is trusted before it is made again
OUTAGE_WAIT_S = 60.0
"""How long a worker waits for an unreachable database to come back before it gives its task
up."""
OUTAGE_RETRIES = 3
"""Times a worker retries its task's step after the database came back (then it fails it)."""
OUTAGE_POLL_S = 0.2  # how often one waiting out an outage asks for the (cached) check
CONNECT_TIMEOUT_S = 5  # a PostgreSQL server that does not answer fails a connection this soon
PROBE_TIMEOUT_S = 3.0
"""A PostgreSQL server that holds its connections but does not answer the check's probe this
soon (hung, or cut off without a word) counts as unreachable."""
READ_TIMEOUT_S = 15.0
"""A request's read that the database has not answered this soon is refused with 503 (its
thread is left to finish when the database answers; writes are never cut short)."""
_TCP_OPTIONS = {
    "keepalives": 1,
    "keepalives_idle": 10,
    "keepalives_interval": 5,
    "keepalives_count": 3,
    "tcp_user_timeout": 15_000,
}
"""libpq's TCP settings: a connection to a server cut off without a word (no FIN, no RST) fails
in about 15 to 25 s, in a query or idle in the pool, instead of after the kernel's minutes."""
IDLE_IN_TRANSACTION_MS = 60_000
"""PostgreSQL ends a session of ours that sits in an open transaction this long without a
statement (``idle_in_transaction_session_timeout``). Our transactions are short (a step
computes outside them); one left open is a backend whose client vanished without a word (a
network cut, a half-open connection), whose row locks would otherwise stall the auction or
job it locked until the server's TCP keepalive gives up, two hours by default."""
DATABASE_RETRY_AFTER_S = 2
"""What a request refused while the database is unavailable is told to wait (``Retry-After``):
a check is trusted ``IDENTITY_CHECK_S``, so writes resume about that soon after it is back."""


class DatabaseUnavailableError(RuntimeError):
    """The database is gone, replaced, or not reachable (503)."""


class WriteLockBusyError(RuntimeError):
    """Another writer holds SQLite's write lock: a write that may not wait did not begin.
    ``in_process``: a thread of this process holds it (``Database.on_write_release`` tells
    when it lets go); else another process does."""

    def __init__(self, message: str, *, in_process: bool) -> None:
        super().__init__(message)
        self.in_process = in_process


def is_database_outage(exc: BaseException) -> bool:
    """Whether ``exc`` says the database could not be used (refused, unreachable, connection
    lost, pool exhausted), as opposed to a statement's own error (a constraint, a bug)."""
    outages = DatabaseUnavailableError | OperationalError | InterfaceError | PoolTimeoutError
    if isinstance(exc, outages):
        return True
    if not isinstance(exc, DBAPIError):
        return False
    return exc.connection_invalidated or getattr(exc.orig, "sqlstate", None) in OUTAGE_STATES


def _write_lock_stalled(exc: BaseException) -> bool:
    """Whether ``exc`` is SQLite's write lock still held by another process at the end of
    the busy timeout."""
    orig = exc.orig if isinstance(exc, DBAPIError) else None
    return getattr(orig, "sqlite_errorname", "") in SQLITE_LOCK_ERRORS


def is_connection_lost(exc: BaseException) -> bool:
    """Whether ``exc`` says the database could not be reached or dropped the connection (a
    stopped or restarting server, a network cut), as opposed to a database that answered but
    was busy: a full connection pool, a lock held too long (SQLite's ``database is locked``), a
    deadlock or a cancelled statement (PostgreSQL's SQLSTATE class 40 and 57014, SQLite's
    interrupt)."""
    if isinstance(exc, DatabaseUnavailableError):
        return True
    if not isinstance(exc, DBAPIError):  # a full pool included
        return False
    if exc.connection_invalidated:
        return True
    state = getattr(exc.orig, "sqlstate", None)
    if state is not None:
        return state.startswith("08") or state in LOST_STATES or state in OUTAGE_STATES
    if getattr(exc.orig, "sqlite_errorname", "") in SQLITE_BUSY_ERRORS:
        return False
    return isinstance(exc, OperationalError | InterfaceError)  # no state: a failed connect


SQLITE_LOCK_ERRORS = {"SQLITE_BUSY", "SQLITE_LOCKED"}
"""SQLite's errors of a write lock held past the busy timeout."""
SQLITE_BUSY_ERRORS = SQLITE_LOCK_ERRORS | {"SQLITE_INTERRUPT"}
"""SQLite's errors of a database that answered: a lock held too long, a statement stopped."""

LOST_STATES = {"57P01", "57P02", "57P03"}
"""PostgreSQL's SQLSTATEs of a server shutting down or starting (``admin_shutdown``,
``crash_shutdown``, ``cannot_connect_now``); class 08 is the connection's own failures."""

OUTAGE_STATES = {"25006"}
"""PostgreSQL's SQLSTATEs that say the database cannot take writes now, whatever the
statement: ``read_only_sql_transaction`` (a standby, or ``default_transaction_read_only`` set
while the server runs)."""


def is_sqlite(url: str) -> bool:
    """True for ``sqlite:`` URLs."""
    return url.startswith("sqlite")


def lease_session_name(owner: str) -> str:
    """The PostgreSQL ``application_name`` of every connection of the server process that
    holds leases as ``owner`` (its API and its workers; not the live updates' listener, which
    holds no lock): how a replica taking over an expired lease finds the sessions of its last
    owner (``crud.end_sessions``)."""
    return "srd-lease-" + hashlib.sha256(owner.encode()).hexdigest()[:16]


def owned_url(url: str, owner: str) -> str:
    """``url`` whose PostgreSQL connections are named for the lease ``owner``
    (``lease_session_name``); a SQLite URL as it is."""
    if is_sqlite(url):
        return url
    named = make_url(url).update_query_dict({"application_name": lease_session_name(owner)})
    return named.render_as_string(hide_password=False)


def sqlite_path(url: str) -> Path:
    """The absolute path of a SQLite URL's database file."""
    database = make_url(url).database
    if not database or database == ":memory:":
        raise ValueError(f"{url}: a file database is needed")
    return Path(database).resolve()


def _open_existing(url: str) -> str:
    """The URL of the same SQLite file, opened read-write but never created."""
    return f"sqlite:///file:{quote(str(sqlite_path(url)))}?mode=rw&uri=true"


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
        self._waiters: list[Callable[[], None]] = []
        self._waiters_lock = threading.Lock()

    def on_release(self, callback: Callable[[], None]) -> None:
        """Call ``callback`` once this process's writer lets go of the lock (from its thread),
        or at once if none holds it."""
        with self._waiters_lock:
            if self._lock.locked():
                self._waiters.append(callback)
                return
        callback()

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

    def begin_at_once(self, connection: Connection) -> None:
        """The begin of a write that may not wait (the event loop's): this process's writer
        lock and SQLite's write lock taken at once, or ``WriteLockBusyError``."""
        if not self._lock.acquire(blocking=False):
            raise WriteLockBusyError("another thread of this process is writing", in_process=True)
        connection.info[self._HELD] = True
        raw: Any = connection.connection.driver_connection
        try:
            raw.execute("PRAGMA busy_timeout=0")
            try:
                raw.execute("BEGIN IMMEDIATE")
            finally:
                raw.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
        except sqlite3.OperationalError as exc:
            self.release(connection.info)
            if _is_busy(exc):
                raise WriteLockBusyError("another process is writing", in_process=False) from exc
            raise OperationalError("BEGIN IMMEDIATE", None, exc) from exc
        except BaseException:
            self.release(connection.info)
            raise

    def on_checkin(self, _dbapi_connection: Any, record: Any) -> None:
        self.release(record.info)

    def release(self, info: dict[Any, Any]) -> None:
        if info.pop(self._HELD, False):
            with self._waiters_lock:
                self._lock.release()
                waiters, self._waiters = self._waiters, []
            for callback in waiters:
                callback()


class JSONText(str):
    """JSON already encoded (a manifest's ``model_dump_json``): a JSON column stores it as it is
    instead of encoding it again."""


def json_dumps(value: Any) -> str:
    """Every JSON column's encoder: ``JSONText`` as it is, anything else by ``json.dumps``."""
    return str.__str__(value) if isinstance(value, JSONText) else json.dumps(value)


def make_engine(url: str, *, create: bool = False) -> Engine:
    """An engine for ``url`` with this project's per-connection settings; a SQLite file must
    exist unless ``create`` (migrations at first start)."""
    if is_sqlite(url):
        return _sqlite_engine(url if create else _open_existing(url), _SqliteWriters())
    return create_engine(
        url,
        pool_pre_ping=True,  # a connection an outage broke is replaced at its next checkout
        pool_size=10,
        max_overflow=20,
        json_serializer=json_dumps,
        **_postgres_options(url),
    )


def _sqlite_engine(url: str, writers: _SqliteWriters, *, at_once: bool = False) -> Engine:
    """A SQLite engine whose writers queue on ``writers``; ``at_once``: one connection whose
    every transaction is a write that begins at once or not at all (``WriteLockBusyError``)."""
    engine = create_engine(
        url,
        connect_args={"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT_MS / 1000},
        json_serializer=json_dumps,
        pool_size=1 if at_once else SQLITE_POOL_SIZE,
        max_overflow=0,
    )
    event.listen(engine, "connect", _sqlite_on_connect)
    event.listen(engine, "begin", writers.begin_at_once if at_once else writers.on_begin)
    event.listen(engine.pool, "checkin", writers.on_checkin)
    return engine


def _postgres_options(url: str) -> dict[str, Any]:
    """libpq's connection timeout, for a PostgreSQL URL: a server that does not answer (a host
    gone from the network) fails a connection in seconds instead of minutes; its TCP settings;
    and ``IDLE_IN_TRANSACTION_MS`` after the URL's own ``options``, if any."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "postgresql":
        return {}
    given = parsed.query.get("options", "")
    bound = f"-c idle_in_transaction_session_timeout={IDLE_IN_TRANSACTION_MS}"
    options = " ".join(
        o for o in ((given if isinstance(given, str) else " ".join(given)), bound) if o
    )
    return {
        "connect_args": {"connect_timeout": CONNECT_TIMEOUT_S, **_TCP_OPTIONS, "options": options}
    }


def _read_only(engine: Engine) -> str:
    """PostgreSQL's ``transaction_read_only`` (``on`` on a standby)."""
    with engine.connect() as connection:
        return str(connection.exec_driver_sql("SHOW transaction_read_only").scalar_one())


def _identity(engine: Engine, url: str) -> tuple[tuple[int, ...], str | None]:
    """What names this very database: the SQLite file's (device, inode), or the PostgreSQL
    database's oid (a dropped and re-created database gets a new one); and on PostgreSQL, the
    schema revision it is at (None: no schema yet, or SQLite, which one server holds)."""
    if is_sqlite(url):
        stat = sqlite_path(url).stat()
        return (stat.st_dev, stat.st_ino), None
    with engine.connect() as connection:
        oid, versioned = connection.exec_driver_sql(
            "SELECT oid, to_regclass('alembic_version') IS NOT NULL FROM pg_database "
            "WHERE datname = current_database()"
        ).one()
        revision = (
            connection.exec_driver_sql("SELECT version_num FROM alembic_version").scalar()
            if versioned
            else None
        )
    return (int(oid),), revision


@functools.cache
def known_revisions() -> frozenset[str]:
    """The schema revisions this release's migrations know (read once per process)."""
    scripts = ScriptDirectory.from_config(alembic_config("sqlite://"))
    return frozenset(script.revision for script in scripts.walk_revisions())


def newer_schema(revision: str) -> str:
    """What a server says once a newer release migrated its database to ``revision``."""
    return (
        f"the database was migrated to schema revision {revision}, which this release does not "
        "know, since this server started: a newer release's server migrated it, and this one "
        "takes no more work. Stop it and run the newer release (docs/server.md, Upgrading)"
    )


class Database:
    """One engine and its two session factories (read and write), tied to the database that
    was there when it was made."""

    def __init__(self, url: str) -> None:
        self.url = url
        self._at_once: Engine | None = None
        self._writers: _SqliteWriters | None = None
        if is_sqlite(url):
            self._writers = writers = _SqliteWriters()
            self.engine = _sqlite_engine(_open_existing(url), writers)
            self._at_once = _sqlite_engine(_open_existing(url), writers, at_once=True)
        else:
            self.engine = make_engine(url)
        self._read = sessionmaker(bind=self.engine, expire_on_commit=False)
        self._writer = self.engine.execution_options(**{_WRITE_OPTION: True})
        self._write = sessionmaker(bind=self._writer, expire_on_commit=False)
        # The checks have a connection of their own: a busy pool is not an outage.
        self._probe = (
            None
            if is_sqlite(url)
            else create_engine(
                url,
                pool_pre_ping=True,
                pool_size=1,
                max_overflow=0,
                pool_timeout=CONNECT_TIMEOUT_S,
                **_postgres_options(url),
            )
        )
        self._prober = (
            None if self._probe is None else ThreadPoolExecutor(1, thread_name_prefix="srd-probe")
        )
        self._probing: Future[Any] | None = None
        self._probe_lock = threading.Lock()
        self._identity, _ = _identity(self._probe or self.engine, url)
        self._checked_at = time.monotonic()
        self._outage_at = -math.inf  # when an operation last met an outage (monotonic)
        self._answered_at = time.time()  # when a statement last came back from the database
        self._outage_began: datetime | None = None  # an outage met, its rounds not pushed back
        self._outage_lock = threading.Lock()
        for engine in (self.engine, self._at_once, self._probe):
            if engine is not None:
                event.listen(engine, "after_cursor_execute", self._answered)
        self._problem: str | None = None
        self._lost = False  # the problem is for good (gone, replaced): no check clears it
        self._check_lock = threading.Lock()

    def problem(self, *, wait: bool = False) -> str | None:
        """Why the database cannot be used, or None. The answer is kept for
        ``IDENTITY_CHECK_S``; a database gone or replaced stays a problem (restart to clear
        it), an unreachable one is checked again and clears once it is back. While another
        thread checks (up to ``PROBE_TIMEOUT_S`` when the database hangs), the last answer
        stands: the event loop asks too, and must never wait on a probe. ``wait`` (a caller
        off the event loop: readiness) waits for that check instead, and makes its own if the
        answer is older than ``IDENTITY_CHECK_S``: the check in progress may predate the ask."""
        acquired = (
            self._check_lock.acquire(timeout=PROBE_TIMEOUT_S + 1.0)
            if wait
            else self._check_lock.acquire(blocking=False)
        )
        if not acquired:
            return self._problem
        try:
            return self._checked()
        finally:
            self._check_lock.release()

    def _checked(self) -> str | None:
        """``problem()`` for a caller that holds the check's lock."""
        if self.check_due():
            self._problem = self._check()
            self._checked_at = time.monotonic()
        return self._problem

    def wait_until_reachable(self, timeout_s: float) -> bool:
        """After an outage met: check again now and then until the database is back (True),
        or for ``timeout_s`` (False; at once if it is gone or replaced for good). Each answer
        comes from a check made after the failure (it waits for one in progress)."""
        deadline = time.monotonic() + timeout_s
        stale = True  # the last check predates the failure
        while True:
            with self._check_lock:  # one hold: nobody else (the event loop) makes this check
                if stale:
                    self._checked_at, stale = -math.inf, False
                problem = self._checked()
            if problem is None:
                return True
            if self._lost or time.monotonic() > deadline:
                return False
            time.sleep(OUTAGE_POLL_S)

    def note_outage(self, exc: BaseException | None = None) -> None:
        """Record that an operation met an outage just now (``since_outage_s``): ``exc``, if
        given, is what it met, recorded only if it says the database itself was out of reach
        (``is_connection_lost``), not busy (a full pool, a deadlock, a cancelled statement),
        or that SQLite's write lock stayed held for the whole busy timeout (another process's
        long transaction: no write could be made all that while, which began that long ago
        at the latest, though reads went on)."""
        stalled = exc is not None and _write_lock_stalled(exc)
        if exc is None or stalled or is_connection_lost(exc):
            with self._outage_lock:
                self._outage_at = time.monotonic()
                # A DatabaseUnavailableError repeats the last check's answer, which met the
                # outage itself: it begins none (after the outage, a stale answer began one).
                if self._outage_began is None and not isinstance(exc, DatabaseUnavailableError):
                    began = self._answered_at
                    if stalled:
                        began = min(began, time.time() - SQLITE_BUSY_TIMEOUT_MS / 1000)
                    self._outage_began = datetime.fromtimestamp(began, UTC)

    def _answered(self, *_: Any) -> None:
        self._answered_at = time.time()

    def hold_claims(self) -> None:
        """No step or job is claimed for the grace after an outage (``since_outage_s``), though
        none was met (a restart with uploads whose retries must come first)."""
        with self._outage_lock:
            self._outage_at = time.monotonic()

    def outage_began(self) -> datetime | None:
        """When an outage this process met began, at the earliest (the last moment a
        statement came back from the database before it), until ``outage_handled``; None:
        none since then."""
        with self._outage_lock:
            return self._outage_began

    def outage_handled(self, began: datetime) -> None:
        """The outage that began at ``began`` is dealt with (its open rounds got their time
        back, in a transaction committed before this call)."""
        with self._outage_lock:
            if self._outage_began == began:
                self._outage_began = None

    def since_outage_s(self) -> float:
        """Seconds since an operation of this process last met an outage (inf: never)."""
        return time.monotonic() - self._outage_at

    @property
    def lost(self) -> bool:
        """The database is gone or replaced for good: no wait brings it back."""
        return self._lost

    def check_due(self) -> bool:
        """Whether the next ``problem()`` makes a check (I/O: run it off the event loop)."""
        return not self._lost and time.monotonic() - self._checked_at > IDENTITY_CHECK_S

    def _probed(self, query: Callable[[Engine], T]) -> T:
        """``query(probe engine)`` in the probe's thread, waited for ``PROBE_TIMEOUT_S`` at most
        (``TimeoutError``); while an earlier probe is still unanswered, none is sent."""
        assert self._prober is not None and self._probe is not None
        with self._probe_lock:
            if self._probing is not None and not self._probing.done():
                raise TimeoutError(f"no answer to a probe within {PROBE_TIMEOUT_S:g} s")
            self._probing = probing = self._prober.submit(query, self._probe)
            try:
                return probing.result(timeout=PROBE_TIMEOUT_S)
            except FutureTimeoutError as exc:
                raise TimeoutError(f"no answer to a probe within {PROBE_TIMEOUT_S:g} s") from exc

    def _check(self) -> str | None:
        try:
            if self._probe is None:
                now, revision = _identity(self.engine, self.url)
            else:
                now, revision = self._probed(lambda probe: _identity(probe, self.url))
        except FileNotFoundError:
            if not self._lost:
                log.warning("the database file %s was deleted", sqlite_path(self.url))
            self._lost = True
            return "the database file was deleted"
        except Exception as exc:  # unreachable: a stopped server, a dropped database
            self.note_outage()
            if self._problem is None:
                log.warning("the database cannot be reached: %s", first_line(exc))
            return UNREACHABLE
        if now != self._identity:
            self._lost = True
            return "the database was replaced by another one since this server started"
        if revision is not None and revision not in known_revisions():
            return self._newer_schema(revision)
        if self._problem is not None:
            log.warning("the database is reachable again")
        return None

    def _newer_schema(self, revision: str) -> str:
        """A newer release migrated the database to ``revision``: lost for good."""
        problem = newer_schema(revision)
        if not self._lost:
            log.warning("%s", problem)
        self._lost = True
        return problem

    def check_revision(self, revision: str | None) -> None:
        """Raise ``DatabaseUnavailableError`` (and stay unavailable for good) if ``revision``,
        read in a transaction about to take work, is one a newer release migrated the database
        to: the check every ``IDENTITY_CHECK_S`` leaves a second in which this server could
        claim what the newer release's servers created."""
        if revision is not None and revision not in known_revisions():
            with self._check_lock:
                self._problem = self._newer_schema(revision)
            raise DatabaseUnavailableError(self._problem)

    def write_problem(self) -> str | None:
        """Why the database cannot take writes now (readiness, off the event loop):
        ``problem(wait=True)``, or it is read-only (a PostgreSQL standby or read-only default;
        a SQLite file, or its folder, that may not be written)."""
        problem = self.problem(wait=True)
        if problem is not None or self._probe is None:
            return problem or _sqlite_write_problem(sqlite_path(self.url))
        try:
            read_only = self._probed(_read_only)
        except Exception as exc:
            log.warning("the database cannot be reached: %s", first_line(exc))
            return UNREACHABLE
        if read_only == "on":
            return "the database is read-only (transaction_read_only is on: a standby?)"
        return None

    def session(self, *, write: bool) -> Session:
        """A new session (``write=True`` takes the write lock at BEGIN on SQLite); raises
        ``DatabaseUnavailableError`` if the database is gone, replaced or unreachable."""
        problem = self.problem()
        if problem is not None:
            raise DatabaseUnavailableError(problem)
        return self._write() if write else self._read()

    @contextmanager
    def transaction(self, *, write: bool) -> Iterator[Connection]:
        """A Core connection in a transaction, committed when the block ends (rolled back on an
        exception): the lighter form of ``session`` for a hot path whose statements are Core
        (``write=True`` as in ``session``); raises ``DatabaseUnavailableError`` the same way."""
        problem = self.problem()
        if problem is not None:
            raise DatabaseUnavailableError(problem)
        with (self._writer if write else self.engine).begin() as connection:
            yield connection

    @property
    def writes_at_once(self) -> bool:
        """Whether ``transaction_at_once`` is available (SQLite)."""
        return self._at_once is not None

    def on_write_release(self, callback: Callable[[], None]) -> None:
        """SQLite: call ``callback`` once the thread of this process that holds the write lock
        lets go of it (from that thread), or at once if none holds it."""
        if self._writers is None:
            raise RuntimeError("on_write_release is for SQLite databases")
        self._writers.on_release(callback)

    @contextmanager
    def transaction_at_once(self) -> Iterator[Connection]:
        """SQLite: a write transaction that never waits, on a connection of its own, for the
        event loop (one caller at a time): its statements run where it is called, without a
        hop to a thread, and it raises ``WriteLockBusyError`` at once, before any statement,
        if another writer holds the lock (write from a thread then: ``transaction``). Raises
        ``DatabaseUnavailableError`` as ``session`` does."""
        if self._at_once is None:
            raise RuntimeError("transaction_at_once is for SQLite databases")
        problem = self.problem()
        if problem is not None:
            raise DatabaseUnavailableError(problem)
        with self._at_once.begin() as connection:
            yield connection

    def close(self) -> None:
        """Release every pooled connection."""
        self.engine.dispose()
        if self._at_once is not None:
            self._at_once.dispose()
        if self._probe is not None:
            self._probe.dispose()
        if self._prober is not None:
            self._prober.shutdown(wait=False, cancel_futures=True)


def _sqlite_write_problem(path: Path) -> str | None:
    """Why SQLite cannot write ``path`` (the folder takes its journal files), or None; named by
    its setting, not its path (readiness is public)."""
    for where, what in ((path, "its file"), (path.parent, "its folder")):
        if not os.access(where, os.W_OK):
            return f"the SQLite database (SRD_DATABASE_URL) cannot be written: {what} is read-only"
    return None


def first_line(exc: BaseException) -> str:
    """An error's first line (its type's name when it has no words)."""
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


UNREACHABLE = "the database cannot be reached (the server's log says why)"
"""What readiness and answers say of an outage. The driver's words (the database's host and
port, its user) go to the server's log only."""
UNAVAILABLE = "the database is unavailable (the server's log says why)"
"""What an answer says of a statement that met an outage (``answer_of_outage``)."""
READ_ONLY = "the database is read-only now (a standby?): it takes no writes"
"""What an answer says of a write the database refused as read-only."""


def answer_of_outage(exc: BaseException) -> str:
    """What an answer says of ``exc``, an outage: never the driver's words, which name the
    database's host, port and user (the server's log has them)."""
    if getattr(getattr(exc, "orig", None), "sqlstate", None) in OUTAGE_STATES:
        return READ_ONLY
    return UNAVAILABLE


def unavailable_message(exc: BaseException) -> str:
    """What the server's log says when the database failed: the first line of the error."""
    return f"the database is unavailable: {first_line(exc)}"


def database_now(session: Session) -> datetime:
    """The time on the database's clock (PostgreSQL: the transaction's start), so that API
    processes on several machines agree on it; this process's clock for SQLite (one process)."""
    if session.get_bind().dialect.name == "sqlite":
        return datetime.now(UTC)
    now: datetime = session.execute(text("SELECT now()")).scalar_one()
    return now.astimezone(UTC)


class ServerAlreadyRunningError(RuntimeError):
    """Another server process serves this SQLite database."""


class SqliteServerLock:
    """The one-server guarantee of a SQLite database: an exclusive ``flock`` on
    ``<database>.serve-lock`` (holding the owner's pid), held while the server runs and
    released by the OS when its process ends, however it ends."""

    def __init__(self, url: str) -> None:
        self.path = sqlite_path(url).with_name(sqlite_path(url).name + ".serve-lock")
        if not self.path.parent.is_dir():  # a mistyped path would otherwise serve a new database
            raise FileNotFoundError(
                f"no folder {self.path.parent} for the SQLite database: create it, or correct "
                "the path"
            )
        self._handle = self.path.open("a+")
        try:
            fcntl.flock(self._handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._handle.seek(0)
            owner = self._handle.read().strip() or "unknown"
            self._handle.close()
            raise ServerAlreadyRunningError(
                f"another srd serve (pid {owner}) is serving the SQLite database "
                f"{sqlite_path(url)}: SQLite serves one server process at a time. To run "
                "several replicas, put them on one PostgreSQL database "
                "(SRD_DATABASE_URL=postgresql+psycopg://...)."
            ) from None
        self._handle.seek(0)
        self._handle.truncate()
        self._handle.write(f"{os.getpid()}\n")
        self._handle.flush()

    def release(self) -> None:
        """Let another server start on the database."""
        if not self._handle.closed:
            fcntl.flock(self._handle, fcntl.LOCK_UN)
            self._handle.close()


def alembic_config(url: str) -> Config:
    """The Alembic configuration, built in code (no ini file needed)."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return config


def upgrade_schema(url: str) -> None:
    """Bring the database at ``url`` to the newest schema (``alembic upgrade head``), creating
    a SQLite file if there is none; each migration is logged. A database whose schema is at a
    revision this release does not know (a newer release wrote it) is refused, untouched."""
    config = alembic_config(url)
    scripts = ScriptDirectory.from_config(config)
    head = scripts.get_current_head()
    current = _revision(url)
    if current is not None and current not in known_revisions():
        raise DatabaseUnavailableError(
            f"the database's schema is at revision {current}, which this release does not know "
            f"(its newest is {head}): a newer release wrote it. Run that release, or restore "
            "the backup taken before the upgrade."
        )
    if current != head:
        shown = make_url(url).render_as_string(hide_password=True)
        log.info("migrating the database %s from %s to %s", shown, current or "empty", head)
    try:
        command.upgrade(config, "head")
    except OperationalError as exc:
        if getattr(exc.orig, "sqlstate", None) != LOCK_NOT_AVAILABLE:
            raise
        raise DatabaseUnavailableError(
            f"a migration waited {MIGRATION_LOCK_TIMEOUT_S:g} s for a table other sessions hold "
            "and stopped, changing nothing: stop every server of the old release before "
            "starting this one (docs/server.md, Upgrading)"
        ) from exc


MIGRATION_LOCK_TIMEOUT_S = 30.0
"""PostgreSQL: how long one migration statement waits for a table's lock (``lock_timeout``)
before the start fails. Waiting longer would queue every query of the old release's servers
behind the migration's ALTER TABLE."""
LOCK_NOT_AVAILABLE = "55P03"
"""PostgreSQL's SQLSTATE for a ``lock_timeout`` reached."""


def _lacking(url: str) -> list[str]:
    """The tables and columns of this release's models that the database at ``url`` does not
    have (none once a release's migrations ran): a revision number says which migrations ran,
    not that they were this release's."""
    from server.store.tables import Base

    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            found = inspect(connection)
            tables = set(found.get_table_names())
            lacking = []
            for table in Base.metadata.sorted_tables:
                if table.name not in tables:
                    lacking.append(f"the table {table.name}")
                    continue
                columns = {column["name"] for column in found.get_columns(table.name)}
                lacking += [
                    f"the column {table.name}.{column.name}"
                    for column in table.columns
                    if column.name not in columns
                ]
            return lacking
    finally:
        engine.dispose()


def _revision(url: str) -> str | None:
    """The schema revision the database at ``url`` is at (None: no schema, or no database)."""
    if not has_schema(url):
        return None
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return MigrationContext.configure(connection).get_current_revision()
    finally:
        engine.dispose()


def prepare_database(url: str, marker: Path) -> None:
    """Migrate the database at ``url`` to the newest schema, refusing to start over a lost one.

    ``marker`` (in the server's data folder) records every database this data folder has
    served. A database without a schema is created only if it is new to the marker: if it
    served before and is now empty or missing, it was deleted or replaced, and the server
    refuses to start rather than quietly begin again with nothing. Replicas starting together
    on one PostgreSQL database take turns (an advisory lock).
    """
    with _migration_lock(url):
        _prepare(url, marker)


MIGRATION_LOCK = 0x5344_4D49_4752
"""The key of the PostgreSQL advisory lock of srd's migrations (``SDMIGR`` in ASCII)."""


@contextmanager
def _migration_lock(url: str) -> Iterator[None]:
    """PostgreSQL: hold a session advisory lock for the block; SQLite: nothing (one server)."""
    if is_sqlite(url):
        yield
        return
    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            held = text("SELECT pg_try_advisory_lock(:key)")
            if not connection.execute(held, {"key": MIGRATION_LOCK}).scalar_one():
                log.info("waiting for another server's migration of the database")
                connection.execute(text("SELECT pg_advisory_lock(:key)"), {"key": MIGRATION_LOCK})
            try:
                yield
            finally:
                connection.execute(text("SELECT pg_advisory_unlock(:key)"), {"key": MIGRATION_LOCK})
    finally:
        engine.dispose()


def _prepare(url: str, marker: Path) -> None:
    key = make_url(url).render_as_string(hide_password=True)
    served: dict[str, str] = json.loads(marker.read_text()) if marker.exists() else {}
    if key in served and not has_schema(url):
        raise DatabaseUnavailableError(
            f"the database {key} served this server before ({served[key]}) but has no schema "
            f"now: it was deleted or replaced. Restore it, or remove its entry from {marker} "
            "to start again with an empty database."
        )
    upgrade_schema(url)
    lacking = _lacking(url)
    if lacking:
        raise DatabaseUnavailableError(
            f"the database {key} is at this release's schema revision but lacks "
            f"{', '.join(lacking[:5])}: a build other than a release migrated it. Restore "
            "the backup taken before, or migrate it with that build's own code."
        )
    if key not in served:
        served[key] = datetime.now(UTC).isoformat(timespec="seconds")
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text(json.dumps(served, indent=2) + "\n")


def has_schema(url: str) -> bool:
    """Whether the database at ``url`` exists and carries this project's schema."""
    if is_sqlite(url) and not sqlite_path(url).exists():
        return False
    engine = make_engine(url)
    try:
        return inspect(engine).has_table("alembic_version")
    finally:
        engine.dispose()
