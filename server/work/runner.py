"""Background work: the one runner of auctions and jobs, claimed from the database with leases.

An auction and a job are both a database row played to its end by a task in a worker process
(``server.work.pool.WorkerPool``): ``server.auctions.steps.AUCTION_WORK`` and
``server.jobs.worker.JOB_WORK``. ``BackgroundRunner`` runs the rows of one ``WorkKind``.

Several API processes (replicas) may share one PostgreSQL database, so a row is played by the
replica that holds its **lease**: ``lease_owner`` (this process's id) and ``lease_expires``.
A thread of each runner passes over its table at once when a row is created or made due here
or, on PostgreSQL, on any replica (``crud.notify_due``: a round that closed on a replica whose
workers are all busy is played by one with a free worker), when a task ends here, at the next
due time it knows of, when its leases need renewing, and at least every ``IDLE_TICK_S`` (for
what other replicas do: rows they release, leases that expire when a replica dies):

* **claims** unfinished rows whose lease is free or expired, as many as its pool has free
  workers, oldest first, with ``SELECT … FOR UPDATE SKIP LOCKED`` (two replicas never claim
  the same row), and queues them on its pool; a job found still running under an expired
  lease goes back to queued first (it runs again from the start);
* **renews** the leases of the rows it plays, every third of ``SRD_LEASE_S``; a row whose
  lease was not renewed (taken over after this replica stalled, or no longer unfinished: a job
  cancelled through another replica) is stopped here;
* **releases** the lease of every row whose task is over.

A replica that dies stops renewing: after ``SRD_LEASE_S`` another claims its rows, and the
auction resumes from its last checkpoint, the job runs again. The workers' own conditional
commits (an auction's round only at the iteration it expects, a job's writes only under the
attempt that claimed it) keep a stale runner from committing a round twice or overwriting a
result, lease or not. Times are the database's clock on PostgreSQL (replicas on several
machines need not agree on theirs).

With SQLite a single server runs (``server.store.db.SqliteServerLock``): there the runner clears the
leases a previous process left at start, and its leases never expire (nobody else could take a
row over).
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy.exc import DBAPIError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from sqlalchemy.orm import Session

from server.store import crud
from server.store.db import (
    Database,
    DatabaseUnavailableError,
    database_now,
    is_database_outage,
    lease_session_name,
    unavailable_message,
)
from server.store.tables import Auction, Job, utcnow
from server.work.pool import TaskFn, WorkerContext, WorkerPool

log = logging.getLogger("srd.runner")

IDLE_TICK_S = 2.0
"""The longest a runner waits between two passes over its table."""
RETRY_S = 0.5
"""The wait after a pass that failed (the database unreachable)."""
CLAIMS_LOGGED = 4096
"""Rows a runner remembers having claimed, so that it logs a row's first claim only."""
OUTAGE_GRACE_S = 5.0
"""A runner claims nothing until this long after this process last met a database outage (its
own passes, the database's probe, or an upload refused for it): the
uploads an outage refused come back first (their arrival remembered, ``server.auctions.uploads``),
before a step closes their round at its deadline. Agents retry after the 503's ``Retry-After``
(2 s), and writes resume about a second after the database is back."""
DUE_MARGIN_S = 0.005
"""A pass for a due time comes this much after it (the row is due by then on the database's
clock too)."""
RENEW_FRACTION = 1 / 3
"""Leases are renewed when this share of their duration has passed."""


@dataclass(frozen=True)
class WorkKind:
    """What a runner plays: the rows of one table, each by one task."""

    name: str
    """``auction`` or ``job``: the pool's and the log's name."""
    table: type[Auction] | type[Job]
    task: TaskFn
    unfinished: Sequence[str]
    """The statuses of a row still to be played."""
    timeout_setting: str
    """The setting of the wall-time limit, as failures name it."""
    died: str
    """The error of a row whose worker died, formatted with its exit ``code``."""
    prepare: Callable[[Session, list[int]], None]
    """Readies rows just claimed for their task (a job left running is queued again)."""
    tasks_per_process: int | None = None
    """Tasks one worker process runs before it is replaced (None: no limit)."""
    due: Any = None
    """The column (``Auction.next_step_at``) whose time must have come for a row to be
    claimed (None: whenever unfinished; a null in the column: at once)."""
    resumable: bool = False
    """A task whose process died is run again (the row resumes from its last commit) rather
    than failed, unless it died ``MAX_DEATHS`` times."""
    progress: Any = None
    """A column that moves on as a resumable row's tasks commit (``Auction.iteration``): a
    death after it moved starts the count of deaths in a row again (None: only a task done
    does)."""
    why_died: Callable[[WorkerContext, int | None], str | None] | None = None
    """A cause of a worker's death that its exit code does not tell, looked for when a row
    fails of it (a job worker that is a Ray driver: its cluster lost), said after ``died``."""
    after_outage: Callable[[Session, datetime, datetime], None] | None = None
    """Called in a write transaction once the database answers again after an outage this
    process met, with when it began (at the earliest) and now (the auctions' open rounds get
    back the time it took: ``crud.push_back_deadlines``)."""


MAX_DEATHS = 3
"""A resumable row whose task's process died this many times in a row, with no task done and
its ``progress`` unmoved in between, is failed (``died``, formatted with ``times`` and the last
exit ``code``): a task that dies before it commits anything, not a row that an outside killer
(memory pressure, an operator) interrupts while it moves on."""


class BackgroundRunner:
    """Plays the rows of one ``WorkKind`` that this process (``owner``) holds the lease of, on
    a pool of ``max_workers`` worker processes, each task stopped after ``timeout_s``."""

    def __init__(
        self,
        database: Database,
        context: WorkerContext,
        kind: WorkKind,
        *,
        max_workers: int,
        timeout_s: float,
        owner: str,
        lease_s: float,
        exclusive: bool,
        ended: Callable[[int], None] | None = None,
    ) -> None:
        self._database = database
        self._context = context
        self._ended = ended  # told of every row whose task ended here (from the pool's thread)
        self.kind = kind
        self.owner = owner
        self._lease = timedelta(seconds=lease_s)
        self._exclusive = exclusive
        self._max_workers = max_workers
        self.pool = WorkerPool(
            name=kind.name,
            task=kind.task,
            context=context,
            max_workers=max_workers,
            on_exit=self._on_exit,
            tasks_per_process=kind.tasks_per_process,
            timeout_s=timeout_s,
            on_timeout=self._on_timeout,
            on_end=self._on_end,
        )
        self._held: set[int] = set()  # rows leased here whose task is not over yet
        self._claimed_before: OrderedDict[int, None] = OrderedDict()
        """Rows claimed here lately (``CLAIMS_LOGGED``): a long auction, claimed again at each
        of its steps, is logged at its first claim only."""
        self._deaths: dict[int, tuple[int, Any]] = {}
        """Resumable rows whose task died: times in a row, and their progress at the last."""
        self._unbegun: dict[int, int] = {}
        """Rows whose worker died before it began their task: times in a row."""
        self._unended: set[str] = set()  # owners whose sessions this role may not end (logged)
        self._over: set[int] = set()  # tasks over, leases to release
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = False
        self._renewed_at: float | None = None  # time.monotonic() of the last renewal
        self._thread = threading.Thread(target=self._run, name=f"{kind.name}-leases", daemon=True)

    def start(self) -> None:
        """Start the pool and the lease thread (which claims every unfinished row it may)."""
        if self._exclusive:
            with self._database.session(write=True) as session:
                crud.clear_leases(session, table=self.kind.table)
                session.commit()
        self.pool.start()
        self._thread.start()

    def submit(self, row_id: int) -> None:
        """A row was created: look for work now (this replica or another will claim it)."""
        self.wake()

    def wake(self) -> None:
        """A row fell due on another replica (or here): look for work now, if a worker is
        free, instead of at the next ``IDLE_TICK_S``."""
        self._wake.set()

    def cancel(self, row_id: int) -> None:
        """Stop a row if it is played here (its row already says why; a replica playing it
        notices when it next renews its leases)."""
        self.pool.cancel(row_id)

    def shutdown(self) -> None:
        """Stop claiming, stop the workers and release every lease held: the rows resume on
        another replica at its next pass, within ``IDLE_TICK_S`` (or at this one's next
        start)."""
        self._stopping = True
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join()
        self.pool.shutdown()
        with self._lock:
            held, self._held = self._held | self._over, set()
            self._over.clear()
        try:
            self._release(held)
        except Exception as exc:  # the server stops all the same: the leases expire
            if not is_database_outage(exc):
                raise
            log.warning(
                "%s: leases of %d rows not released (%s): they expire within the lease",
                self.kind.name,
                len(held),
                unavailable_message(exc),
            )

    @property
    def held(self) -> set[int]:
        """The rows this runner plays now."""
        with self._lock:
            return set(self._held)

    def _run(self) -> None:
        failing = False  # an outage is logged once, not at every pass
        wait = 0.0  # the first pass at once
        while True:
            self._wake.wait(wait)
            self._wake.clear()
            if self._stopping:
                return
            try:
                wait = self._tick()
            except Exception as exc:  # the leases last: try again soon
                if not is_database_outage(exc):
                    log.exception("%s leases: a pass failed", self.kind.name)
                else:
                    self._database.note_outage(exc)
                    if not failing:
                        log.warning(
                            "%s leases: %s; retrying", self.kind.name, unavailable_message(exc)
                        )
                failing = True
                wait = RETRY_S
            else:
                failing = False

    def _tick(self) -> float:
        """One pass: release what ended, renew, claim; the seconds until the next pass."""
        with self._lock:
            over, self._over = self._over, set()
            self._held -= over
        try:
            self._release(over)
        except Exception:
            with self._lock:  # released at a later pass
                self._over |= over
            raise
        self._after_outage()
        wait = IDLE_TICK_S
        if not self._exclusive:
            wait = min(wait, self._renew())
        with self._lock:
            free = self._max_workers - len(self._held)
        if free > 0:
            claimed, due_in = self._claim(free)
            for row_id in claimed:
                self.pool.submit(row_id)
            if due_in is not None:
                wait = min(wait, due_in)
        return wait

    def _after_outage(self) -> None:
        """Once the database answers again after an outage this process met, the kind's
        ``after_outage``, at once (before the grace ends and any step is claimed)."""
        began = self._database.outage_began()
        if began is None or self.kind.after_outage is None:
            return
        with self._database.session(write=True) as session:
            self.kind.after_outage(session, began, utcnow())
            session.commit()
        self._database.outage_handled(began)

    def _claim(self, limit: int) -> tuple[list[int], float | None]:
        """The rows claimed now, and while workers stay free, the seconds until the next
        unleased row falls due (None: none is waiting for a time, or no worker is free).
        Nothing is claimed within ``OUTAGE_GRACE_S`` of an outage; meanwhile the read is
        made every ``RETRY_S``, so that an outage still going on is met (and the grace counts
        from its end, not from the last time it was noticed)."""
        with self._database.session(write=False) as session:  # most passes find nothing
            now = database_now(session)
            found = self._claimable(session, now, limit, lock=False)
            if not found:
                return [], self._due_in(session, now)
        grace_s = OUTAGE_GRACE_S - self._database.since_outage_s()
        if grace_s > 0:
            return [], min(grace_s, RETRY_S)
        with self._database.session(write=True) as session:
            if not self._exclusive:  # replicas: not if a newer release migrated it meanwhile
                self._database.check_revision(crud.schema_revision(session))
            now = database_now(session)
            claimed = self._claimable(session, now, limit, lock=True)
            if len(claimed) < len(found) and not self._exclusive:  # some were locked
                self._end_stale_sessions(session, now, set(found) - set(claimed))
            if claimed:
                self.kind.prepare(session, claimed)
                crud.take_leases(
                    session,
                    table=self.kind.table,
                    row_ids=claimed,
                    owner=self.owner,
                    expires=None if self._exclusive else now + self._lease,  # None: never
                )
            due_in = self._due_in(session, now) if len(claimed) < limit else None
            session.commit()
        with self._lock:
            self._held.update(claimed)
        for row_id in claimed:
            again = row_id in self._claimed_before
            self._claimed_before[row_id] = None
            self._claimed_before.move_to_end(row_id)
            if len(self._claimed_before) > CLAIMS_LOGGED:
                self._claimed_before.popitem(last=False)
            log.log(
                logging.DEBUG if again else logging.INFO,
                "%s %d claimed by %s",
                self.kind.name,
                row_id,
                self.owner,
            )
        return claimed, due_in

    def _end_stale_sessions(self, session: Session, now: datetime, skipped: set[int]) -> None:
        """Rows free to claim were locked (PostgreSQL skipped them): end the sessions of the
        owners whose leases on those rows expired, so that the next pass claims them. A replica
        frozen inside a transaction (a paused process or VM) holds its row locks until its
        connection breaks; its lease's expiry is the sign that it is gone
        (``lease_session_name``). A session this role may not end (another role's) is left,
        and the claim goes on."""
        if session.get_bind().dialect.name != "postgresql":
            return
        stale = crud.expired_owners(
            session,
            table=self.kind.table,
            unfinished=self.kind.unfinished,
            now=now,
            other_than=self.owner,
            row_ids=skipped,
        )
        if stale:
            try:
                with session.begin_nested():  # a refusal undoes this alone, not the claim
                    ended = crud.end_sessions(session, [lease_session_name(o) for o in stale])
            except DBAPIError as exc:
                if set(stale) <= self._unended:  # said once, not at every pass
                    return
                self._unended.update(stale)
                log.warning(
                    "%s: could not end the database sessions of %s, whose leases expired "
                    "holding locks: %s",
                    self.kind.name,
                    ", ".join(stale),
                    str(exc.orig).splitlines()[0] if exc.orig is not None else exc,
                )
                return
            if ended:
                log.warning(
                    "%s: ended %d database sessions of %s, whose leases expired holding locks",
                    self.kind.name,
                    ended,
                    ", ".join(stale),
                )

    def _due_in(self, session: Session, now: datetime) -> float | None:
        """Seconds until the earliest unfinished row without a live lease falls due."""
        kind = self.kind
        if kind.due is None:
            return None
        earliest = crud.earliest_due(
            session, table=kind.table, unfinished=kind.unfinished, due=kind.due, now=now
        )
        if earliest is None:
            return None
        return max((earliest - now).total_seconds(), 0.0) + DUE_MARGIN_S

    def _claimable(self, session: Session, now: datetime, limit: int, *, lock: bool) -> list[int]:
        """Unfinished rows with no lease or an expired one, except those played here (their
        lease is renewed, not claimed again)."""
        with self._lock:
            held = set(self._held)
        kind = self.kind
        return crud.claimable(
            session,
            table=kind.table,
            unfinished=kind.unfinished,
            due=kind.due,
            now=now,
            held=held,
            limit=limit,
            lock=lock,
        )

    def _renew(self) -> float:
        """Renew the leases held here when a share of their duration has passed; the seconds
        until the next renewal."""
        with self._lock:
            held = set(self._held)
        every = self._lease.total_seconds() * RENEW_FRACTION
        if not held:
            return IDLE_TICK_S
        since = None if self._renewed_at is None else time.monotonic() - self._renewed_at
        if since is not None and since < every:
            return every - since
        with self._database.session(write=True) as session:
            now = database_now(session)
            kept = crud.renew_leases(
                session,
                table=self.kind.table,
                unfinished=self.kind.unfinished,
                row_ids=held,
                owner=self.owner,
                expires=now + self._lease,
            )
            lost = held - kept
            stop = (
                crud.stopped_elsewhere(
                    session, table=self.kind.table, unfinished=self.kind.unfinished, row_ids=lost
                )
                if lost
                else set()
            )
            session.commit()
        self._renewed_at = time.monotonic()
        for row_id in stop:  # cancelled, or taken over (a row its task just ended is not)
            log.warning("%s %d: lease lost; stopped here", self.kind.name, row_id)
            self.pool.cancel(row_id)
        return every

    def _release(self, row_ids: set[int]) -> None:
        if not row_ids:
            return
        with self._database.session(write=True) as session:
            crud.release_leases(session, table=self.kind.table, row_ids=row_ids, owner=self.owner)
            session.commit()

    def _on_end(self, row_id: int, done: bool) -> None:
        """A row's task is over (done, died, stopped or dropped): its lease is released. A
        task done resets the row's deaths: they count in a row."""
        with self._lock:
            self._over.add(row_id)
            if done:
                self._deaths.pop(row_id, None)
                self._unbegun.pop(row_id, None)
        self._wake.set()
        if self._ended is not None:
            self._ended(row_id)

    def _on_exit(self, row_id: int, exit_code: int | None, began: bool) -> None:
        """The worker process died in the middle of this row (killed, crashed): a resumable
        row is run again from its last commit (its lease is released with the task's end), and
        so is any row whose worker was stopped by SIGTERM or SIGINT from outside (a service
        manager stopping every process of the service: the API is stopping too). A worker that
        died before it began the row's task (``began`` False) ran none of it: the death is not
        counted as the task's, and the row runs again, unless workers died so ``MAX_DEATHS``
        times in a row for it (a worker that cannot start: the row fails saying so)."""
        with self._lock:
            unbegun = 0 if began else self._unbegun.get(row_id, 0) + 1
            if 0 < unbegun < MAX_DEATHS:
                self._unbegun[row_id] = unbegun
            else:
                self._unbegun.pop(row_id, None)
        if unbegun >= MAX_DEATHS:
            self._fail(
                row_id,
                f"its worker died before it began, {unbegun} times in a row (last exit code "
                f"{exit_code}): a worker process cannot start",
            )
            return
        if unbegun:
            log.warning("%s %d: its worker died (code %s) before it began; running it again",
                        self.kind.name, row_id, exit_code)  # fmt: skip
            return
        stops = (signal.SIGTERM, signal.SIGINT)  # died of one, or exited 128 + it (a Ray driver)
        interrupted = exit_code in {code for n in stops for code in (-n, 128 + n)}
        if self.kind.resumable or interrupted:
            progress = self._progress(row_id)
            with self._lock:
                times, before = self._deaths.get(row_id, (0, None))
                times = 1 if times and progress is not None and progress != before else times + 1
                self._deaths[row_id] = (times, progress)
            if times < MAX_DEATHS:
                log.warning("%s %d: its worker died (code %s); resuming", self.kind.name, row_id,
                            exit_code)  # fmt: skip
                return
            with self._lock:
                self._deaths.pop(row_id, None)
        else:
            times = 1
        died = self.kind.died.format(code=exit_code, times=times)
        why = self.kind.why_died
        cause = why(self._context, exit_code) if why is not None else None
        self._fail(row_id, f"{died}: {cause}" if cause else died)

    def _progress(self, row_id: int) -> Any:
        """The row's ``progress`` now (None without one, or with the database away: then
        the death counts as one more in a row)."""
        if self.kind.progress is None:
            return None
        try:
            with self._database.session(write=False) as session:
                return crud.progress_of(session, column=self.kind.progress, row_id=row_id)
        except (DBAPIError, DatabaseUnavailableError, PoolTimeoutError):
            return None

    def _on_timeout(self, row_id: int, limit_s: float) -> None:
        name, setting = self.kind.name, self.kind.timeout_setting
        self._fail(row_id, f"stopped at the {name} time limit of {limit_s:g} s ({setting})")

    def _fail(self, row_id: int, error: str) -> None:
        log.warning("%s %d failed: %s", self.kind.name, row_id, error)
        with self._database.session(write=True) as session:
            crud.fail_unfinished(session, table=self.kind.table, row_id=row_id, error=error)
            session.commit()
