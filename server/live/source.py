"""The live-update source of an API process, shared by the event streams
(``server.live.events``), the long polls of ``GET /auctions/{id}/rounds/current`` and the round
sockets (``server.live.rounds``).

Whatever listens reads committed rows, never another process's memory, so every API replica
sharing the database shows the same. A listener watches a row (an auction or a job) through a
**view** (what it shows of the row: an event stream's rounds, a long poll's newest round); the
source keeps one **feed** per (row, view), shared by all its listeners in this process.

The source reads the state of the watched rows, batched (one query for all watched auctions,
one for all watched jobs), and rebuilds a row's feeds only when its state changed: a changed
row is read once, and every listener of it wakes. It reads them

* on SQLite, every ``SRD_EVENT_POLL_INTERVAL_S`` while anyone listens, if anything was committed
  since the last read (``PRAGMA data_version``, a few microseconds: an interval in which nothing
  was committed reads nothing);
* on PostgreSQL, when a commit announces the row on the ``LISTEN``/``NOTIFY`` channel
  (``server.store.crud.live``): one dedicated connection per process listens from its start,
  reconnects after an outage (every watched row is read again then, for what it missed;
  meanwhile the rows are read as on SQLite) and, as a safety net, every
  ``SRD_LIVE_SAFETY_POLL_S``. The channel also says when work falls due (``due:<kind>``): the
  process's runner of that kind is woken (``when_due``).

A change this process makes itself is read at once (``poke``), and on SQLite so is a row whose
auction step or job, run by one of this process's workers, just ended (``committed_elsewhere``):
a round a step opened reaches its agents without waiting for the next poll.
"""

from __future__ import annotations

import asyncio
import logging
import sqlite3
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager, suppress
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import psycopg
from sqlalchemy import make_url
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from server.store import crud
from server.store.db import (
    CONNECT_TIMEOUT_S,
    PROBE_TIMEOUT_S,
    READ_TIMEOUT_S,
    Database,
    DatabaseUnavailableError,
    answer_of_outage,
    is_database_outage,
    is_sqlite,
    sqlite_path,
    unavailable_message,
)

log = logging.getLogger("srd.live")

DUE_DELAY_S = 0.05
"""A runner is woken by the channel's ``due:<kind>`` this long after it (at most once in that
time, however many come): the process that made the work due wakes its own runner at once and
keeps the work when it has a worker free, as it did before any other heard; the others pass
after, and take the work only if it could not."""
RECONNECT_S = 0.5
"""Pause before the listening connection is opened again after it failed."""
STALL_S = PROBE_TIMEOUT_S
"""On PostgreSQL, a read not answered this soon counts as an outage while it goes on (a server
that hangs, or is cut off without a word); the next read is made once it ends."""
LISTENER_NAME = "srd-live"
"""``application_name`` of the listening connection (how an operator finds it)."""

S = TypeVar("S")
Key = tuple[crud.LiveKind, int]
View = Callable[[Session, int, Any, "S | None"], S]
"""``(session, row id, row state, previous snapshot) -> snapshot``: what a listener shows of a
row, built from its state (``crud.AuctionState``, ``crud.JobState``; None when the row is gone)
and the previous snapshot (so reads can be incremental)."""

_STATES: dict[crud.LiveKind, Callable[[Session, list[int]], dict[int, Any]]] = {
    "auction": lambda session, ids: crud.auction_states(session, auction_ids=ids),
    "job": lambda session, ids: crud.job_states(session, job_ids=ids),
}


@dataclass(eq=False)
class Feed(Generic[S]):
    """One view of one row, shared by its listeners in this process."""

    view: View[S]
    snapshot: S | None = None
    built: bool = False
    """``snapshot`` has been read (it may be None: a view's "no such row")."""
    generation: int = 0
    """Bumped whenever ``snapshot`` changes."""
    listeners: int = 0
    failure: BaseException | None = None
    """Why the last read failed: before the first snapshot any failure, after it an outage
    (``raise_failure``); cleared by the next read that succeeds."""
    _changed: asyncio.Event = field(default_factory=asyncio.Event)

    def raise_failure(self) -> None:
        """Raise why the last read failed, if it did: a database outage as
        ``DatabaseUnavailableError`` (503), anything else as it was."""
        if self.failure is None:
            return
        if is_database_outage(self.failure):
            raise DatabaseUnavailableError(answer_of_outage(self.failure))
        raise self.failure

    async def wait(self, generation: int, timeout_s: float) -> bool:
        """Wait until the snapshot is newer than ``generation``; False on timeout."""
        if self.generation != generation:
            return True
        try:  # not wait_for: on Python 3.11 it can swallow a cancellation that meets a wake-up
            async with asyncio.timeout(timeout_s):
                await self._changed.wait()
        except TimeoutError:
            return False
        return True

    def _wake(self) -> None:
        woken, self._changed = self._changed, asyncio.Event()
        woken.set()

    def _publish(self, snapshot: S | None) -> None:
        self.snapshot, self.built, self.failure = snapshot, True, None
        self.generation += 1
        self._wake()


@dataclass(eq=False)
class _Row:
    """A watched row: its state as last read, and its feeds."""

    state: Any = None
    read: bool = False
    feeds: dict[View[Any], Feed[Any]] = field(default_factory=dict)


class _SqliteCommits:
    """Whether a SQLite database saw a commit since the last look: ``PRAGMA data_version`` on a
    read-only connection of its own (it moves with every commit made on another connection; it
    takes no lock). Any error answers True, so the rows are read as without it."""

    def __init__(self, url: str) -> None:
        self._uri = sqlite_path(url).as_uri() + "?mode=ro"
        self._connection: sqlite3.Connection | None = None
        self._seen: int | None = None

    def since_last(self) -> bool:
        try:
            if self._connection is None:
                self._connection = sqlite3.connect(self._uri, uri=True, isolation_level=None)
            (version,) = self._connection.execute("PRAGMA data_version").fetchone()
        except sqlite3.Error:
            self.close()
            return True
        changed, self._seen = version != self._seen, version
        return bool(changed)

    def close(self) -> None:
        if self._connection is not None:
            self._connection.close()
        self._connection, self._seen = None, None


_Plan = list[tuple[Key, Any, bool, list[tuple[Feed[Any], Any, bool]]]]
"""What one read does, per row: (key, state known, whether it is known, [(feed, its snapshot,
whether it is built)])."""
_Result = list[tuple[Key, Any, list[tuple[Feed[Any], Any]]]]
"""What one read found, per row: (key, state, [(feed, new snapshot)])."""


class LiveSource:
    """The one live-update source of an API process (see the module docstring)."""

    def __init__(self, database: Database, *, poll_s: float, safety_poll_s: float) -> None:
        self._database = database
        self._listens = not is_sqlite(database.url)
        self._commits = None if self._listens else _SqliteCommits(database.url)
        self.interval_s = safety_poll_s if self._listens else poll_s
        self._poll_s = poll_s
        self._rows: dict[Key, _Row] = {}
        self._dirty: set[Key] = set()
        self._wake = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self.reads = 0
        """Reads made so far (each: one query per kind of row it reads)."""
        self.listening = False
        """The listening connection is open (always False on SQLite)."""
        self.draining = False
        """The server is shutting down: long polls answer now instead of waiting."""
        self._due: dict[str, Callable[[], None]] = {}
        self._due_soon: set[str] = set()  # kinds whose runner is woken within DUE_DELAY_S

    def when_due(self, kind: crud.LiveKind, wake: Callable[[], None]) -> None:
        """Call ``wake`` (on the event loop, ``DUE_DELAY_S`` later) when a commit announces a
        row of ``kind`` due (``crud.notify_due``, on PostgreSQL: any replica's commit)."""
        self._due[kind] = wake

    def start(self) -> None:
        """On PostgreSQL, listen from now on (due rows are heard with nobody watching);
        elsewhere reads start with the first listener."""
        if self._listens:
            self._start()

    @property
    def watched(self) -> int:
        """How many rows are watched right now."""
        return len(self._rows)

    @asynccontextmanager
    async def watch(
        self, kind: crud.LiveKind, row_id: int, view: View[S]
    ) -> AsyncIterator[Feed[S]]:
        """Listen to the feed of ``view`` on the row (made on first use), once its first
        snapshot is read (its failure is raised; ``DatabaseUnavailableError`` if none comes
        within ``READ_TIMEOUT_S``: a feed made while a read hangs is not part of that read, and
        would wait for the database as long as it hangs); leaving the block drops the feed when
        nobody else listens to it, and the row when nobody watches it."""
        self._start()
        key = (kind, row_id)
        row = self._rows.setdefault(key, _Row())
        feed: Feed[S] | None = row.feeds.get(view)
        if feed is None:
            feed = row.feeds[view] = Feed(view)
            self._mark(key)
        feed.listeners += 1
        try:
            deadline = asyncio.get_running_loop().time() + READ_TIMEOUT_S
            while True:  # a snapshot the last read could not confirm is not served
                feed.raise_failure()
                if feed.built:
                    break
                left = deadline - asyncio.get_running_loop().time()
                if left <= 0:
                    raise DatabaseUnavailableError(f"no answer within {READ_TIMEOUT_S:g} s")
                await feed.wait(feed.generation, min(self.interval_s, left))
            yield feed
        finally:  # no await here: this also runs when the listener's task is cancelled
            feed.listeners -= 1
            if feed.listeners == 0:
                del row.feeds[view]
                if not row.feeds:
                    del self._rows[key]

    def poke(self, kind: crud.LiveKind, row_id: int) -> None:
        """This process changed the row: read it again now."""
        if (kind, row_id) in self._rows:
            self._mark((kind, row_id))

    def committed_elsewhere(self, kind: crud.LiveKind, row_id: int) -> None:
        """Another process of this server committed a change to the row (an auction's step
        ended; from any thread): on SQLite it is read now, not at the next poll (on PostgreSQL
        its ``NOTIFY`` tells)."""
        loop = self._loop
        if loop is not None and not self._listens:
            with suppress(RuntimeError):  # the loop closed meanwhile
                loop.call_soon_threadsafe(self.poke, kind, row_id)

    def drain(self) -> None:
        """The server is shutting down: wake every listener (a long poll then answers with
        what it has, so the shutdown does not wait out its ``wait``)."""
        self.draining = True
        for row in self._rows.values():
            for feed in row.feeds.values():
                feed._wake()

    async def close(self) -> None:
        """Stop reading and listening (the listeners keep their last snapshots)."""
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        if self._commits is not None:
            self._commits.close()

    def _mark(self, key: Key) -> None:
        self._dirty.add(key)
        self._wake.set()

    def _start(self) -> None:
        if self._tasks:
            return
        self._loop = loop = asyncio.get_running_loop()
        self._tasks.append(loop.create_task(self._read_loop(), name="live reads"))
        if self._listens:
            self._tasks.append(loop.create_task(self._listen(), name="live listener"))

    async def _read_loop(self) -> None:
        failing = False  # an outage is logged once, not at every read
        while True:
            if not self._dirty:
                # while the listener is down, PostgreSQL is polled as SQLite is
                interval = self._poll_s if self._listens and not self.listening else self.interval_s
                try:
                    async with asyncio.timeout(interval if self._rows else None):
                        await self._wake.wait()
                except TimeoutError:  # the poll (on PostgreSQL the safety net)
                    if self._commits is None or self._commits.since_last():
                        self._dirty.update(self._rows)
            self._wake.clear()
            keys, self._dirty = self._dirty & self._rows.keys(), set()
            if not keys:
                continue
            plan: _Plan = [
                (
                    key,
                    self._rows[key].state,
                    self._rows[key].read,
                    [(f, f.snapshot, f.built) for f in self._rows[key].feeds.values()],
                )
                for key in keys
            ]
            reading = asyncio.ensure_future(run_in_threadpool(self._read, plan))
            try:
                if self._listens and not (await asyncio.wait({reading}, timeout=STALL_S))[0]:
                    stalled = DatabaseUnavailableError(f"no answer within {STALL_S:g} s")
                    if not failing:
                        log.warning("live updates: the database did not answer a read in time")
                    failing = True
                    self._failed(plan, stalled)
                found = await reading  # however long: one read at a time
            except Exception as exc:  # read again later
                if not is_database_outage(exc):
                    log.exception("live updates: reading failed; retrying")
                elif not failing:
                    log.warning("live updates: %s; retrying", unavailable_message(exc))
                failing = True
                self._failed(plan, exc)
                await self._pause()
                self._dirty.update(keys)
                continue
            if failing:
                log.info("live updates: reading again")
            failing = False
            self.reads += 1
            self._deliver(found)

    @staticmethod
    def _failed(plan: _Plan, exc: BaseException) -> None:
        """A read of the planned rows failed: a feed without a snapshot fails its listeners;
        in an outage every feed does (new listeners, long polls and round sockets are answered
        503 instead of a snapshot the database can no longer confirm; event streams wait)."""
        outage = is_database_outage(exc)
        for _, _, _, feeds in plan:
            for feed, _, built in feeds:
                if outage or not built:
                    feed.failure = exc
                    feed._wake()

    async def _pause(self) -> None:
        """Wait ``interval_s``, or less if a notification or a new listener comes."""
        with suppress(TimeoutError):
            async with asyncio.timeout(self.interval_s):
                await self._wake.wait()

    def _read(self, plan: _Plan) -> _Result:
        """One read (in the thread pool): the states of the planned rows, one query per kind,
        then the feeds of every row whose state changed and every feed not built yet."""
        ids: dict[crud.LiveKind, list[int]] = {}
        for (kind, row_id), *_ in plan:
            ids.setdefault(kind, []).append(row_id)
        found: _Result = []
        with self._database.session(write=False) as session:
            states = {kind: _STATES[kind](session, row_ids) for kind, row_ids in ids.items()}
            for key, known, was_read, feeds in plan:
                state = states[key[0]].get(key[1])
                changed = not was_read or state != known
                snapshots = [
                    (feed, feed.view(session, key[1], state, previous))
                    for feed, previous, built in feeds
                    if changed or not built
                ]
                found.append((key, state, snapshots))
        return found

    def _deliver(self, found: _Result) -> None:
        for key, state, snapshots in found:
            row = self._rows.get(key)
            if row is None:  # nobody watches it any more
                continue
            row.state, row.read = state, True
            for feed in row.feeds.values():
                feed.failure = None  # read again: what it holds is confirmed
            for feed, snapshot in snapshots:
                if row.feeds.get(feed.view) is feed and (
                    not feed.built or snapshot is not feed.snapshot
                ):
                    feed._publish(snapshot)

    async def _listen(self) -> None:
        """Keep one connection listening on the channel; a notified row that is watched is
        read at once."""
        url = make_url(self._database.url).set(drivername="postgresql")
        conninfo = url.render_as_string(hide_password=False)
        failing = False
        while True:
            try:
                connection = await psycopg.AsyncConnection.connect(
                    conninfo,
                    autocommit=True,
                    connect_timeout=CONNECT_TIMEOUT_S,
                    application_name=LISTENER_NAME,
                    # a connection cut off without a word is noticed in under a minute
                    keepalives=1,
                    keepalives_idle=10,
                    keepalives_interval=5,
                )
                async with connection:
                    await connection.execute(f"LISTEN {crud.LIVE_CHANNEL}")
                    self.listening = True
                    if failing:
                        log.info("live updates: listening again")
                    failing = False
                    self._dirty.update(self._rows)  # what changed while nobody listened
                    self._wake.set()
                    async for notice in connection.notifies():
                        self._notified(notice.payload)
            except Exception as exc:  # refused, dropped, killed: connect again
                if not failing:
                    log.warning(
                        "live updates: the listening connection failed: %s; reconnecting", exc
                    )
                failing = True
            finally:
                self.listening = False
                self._wake.set()  # the read loop polls meanwhile
            await asyncio.sleep(RECONNECT_S)

    def _wake_runner(self, kind: str) -> None:
        self._due_soon.discard(kind)
        self._due[kind]()

    def _notified(self, payload: str) -> None:
        kind, _, row_id = payload.partition(":")
        if kind == "due":
            if row_id in self._due and row_id not in self._due_soon:
                self._due_soon.add(row_id)
                asyncio.get_running_loop().call_later(DUE_DELAY_S, self._wake_runner, row_id)
        elif kind in _STATES and row_id.isdigit() and (kind, int(row_id)) in self._rows:
            self._mark((kind, int(row_id)))
