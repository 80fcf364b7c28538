"""Work handed from event loops to one thread that does it in groups, and the group-commit
writer built on it (``POST /submit``, the uploads of remote rounds and their lookups use them).

``GroupWorker``: a request on any event loop queues an item and awaits its result; one thread
takes every item queued since its last pass (at most ``MAX_GROUP``, in arrival order; with a
``gather_gap_s``, also each item that comes within that long of the one before), hands the
group to one function that returns a result per item (or an exception to raise in that item's
waiter), and gives each result back to its waiter's future on the waiter's own loop. Under no
load a group is one item, which waits at most the gap for company; under load the round trips
and wake-ups are shared by the group.

``GroupTransaction`` (on the caller's thread) and ``GroupWriter`` (a ``GroupTransaction`` fed
by its own ``GroupWorker``): the group is decided and written in ONE transaction. If a
statement hits a unique constraint (a row written meanwhile by another process), the group is
rolled back and each of its items is written again in a transaction of its own, so only the
one at fault gets the conflict answer; if the database itself fails, every item of the group
gets the unavailable answer and nothing of the group is stored.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import queue
import threading
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from server.db import Database, is_database_outage

log = logging.getLogger("srd.grouping")

MAX_GROUP = 64
"""Items per group (per transaction), at most."""
STOP_GRACE_S = 10.0
"""How long ``shutdown`` waits for the thread to finish what is queued."""

Item = TypeVar("Item")
Result = TypeVar("Result")


class StoppingError(RuntimeError):
    """The worker is shutting down and takes no new item."""


@dataclass
class _Waiting(Generic[Item, Result]):
    item: Item
    loop: asyncio.AbstractEventLoop
    future: asyncio.Future[Result]


class GroupWorker(Generic[Item, Result]):
    """``await put(item)`` from any event loop; ``handle`` runs on one thread, a group at a
    time. ``on_error`` turns a failure of ``handle`` into every waiter's result (or exception);
    ``after_pass`` runs after every pass, and at least every ``idle_s`` seconds when given."""

    def __init__(
        self,
        name: str,
        handle: Callable[[list[Item]], Sequence[Result | BaseException]],
        *,
        on_error: Callable[[Exception], Result | BaseException],
        idle_s: float | None = None,
        after_pass: Callable[[], None] | None = None,
        gather_gap_s: float = 0.0,
    ) -> None:
        self._name = name
        self._handle = handle
        self._on_error = on_error
        self._idle_s = idle_s
        self._gap_s = gather_gap_s
        self._after_pass = after_pass
        self._queue: queue.SimpleQueue[_Waiting[Item, Result] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._closed = False

    def start(self) -> None:
        self._thread.start()

    def put(self, item: Item) -> asyncio.Future[Result]:
        """Queue ``item`` from the running event loop; the future of its result. Raises
        ``StoppingError`` once ``shutdown`` has begun."""
        if self._closed:
            raise StoppingError(f"{self._name} is stopping")
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Result] = loop.create_future()
        self._queue.put(_Waiting(item, loop, future))
        return future

    def shutdown(self) -> None:
        """Do what is queued, then stop the thread."""
        self._closed = True
        self._queue.put(None)
        if self._thread.is_alive():
            self._thread.join(STOP_GRACE_S)

    def _run(self) -> None:
        stopping = False
        while not stopping:
            group, stopping = self._next_group()
            if group:
                _hand_back(group, self._results([waiting.item for waiting in group]))
            if self._after_pass is not None:
                try:
                    self._after_pass()
                except Exception:  # never let the thread die
                    log.exception("%s: the work after a pass failed", self._name)

    def _next_group(self) -> tuple[list[_Waiting[Item, Result]], bool]:
        """The items queued since the last pass (waiting up to ``idle_s`` for the first) and
        each that comes within ``gather_gap_s`` of the one before, and whether ``shutdown`` has
        asked the thread to stop after them."""
        try:
            waiting = self._queue.get(timeout=self._idle_s)
        except queue.Empty:
            return [], False
        group: list[_Waiting[Item, Result]] = []
        while waiting is not None:
            group.append(waiting)
            if len(group) == MAX_GROUP:
                return group, False
            try:
                waiting = self._queue.get(timeout=self._gap_s)  # 0: what is queued now
            except queue.Empty:
                return group, False
        return group, True

    def _results(self, items: list[Item]) -> Sequence[Result | BaseException]:
        try:
            return self._handle(items)
        except Exception as exc:  # never let the thread die: every waiter gets the failure
            log.exception("%s: a group of %d failed", self._name, len(items))
            return [self._on_error(exc)] * len(items)


def _hand_back(
    group: list[_Waiting[Item, Result]], results: Sequence[Result | BaseException]
) -> None:
    """Give results computed on the thread to the futures awaited on their event loops."""
    by_loop: dict[
        asyncio.AbstractEventLoop, list[tuple[asyncio.Future[Result], Result | BaseException]]
    ] = defaultdict(list)
    for waiting, result in zip(group, results, strict=True):
        by_loop[waiting.loop].append((waiting.future, result))
    for loop, answers in by_loop.items():
        with contextlib.suppress(RuntimeError):  # that loop has closed: nobody waits
            loop.call_soon_threadsafe(_settle, answers)


def _settle(answers: list[tuple[asyncio.Future[Result], Result | BaseException]]) -> None:
    for future, result in answers:
        if future.done():
            continue
        if isinstance(result, BaseException):
            future.set_exception(result)
        else:
            future.set_result(result)


class _ConflictError(Exception):
    """A statement of the group hit a unique constraint."""


class GroupTransaction(Generic[Item, Result]):
    """``write_group(group)`` on the caller's thread: ``decide`` decides a group in arrival
    order and writes it in the session it is given, committed here (see the module docstring).

    ``conflict`` is an item's answer when its own write hits a unique constraint,
    ``unavailable`` every item's answer when the database fails; ``after_commit`` is told each
    group once it is committed."""

    def __init__(
        self,
        name: str,
        database: Database,
        decide: Callable[[Session, list[Item]], list[Result]],
        *,
        conflict: Callable[[Item], Result],
        unavailable: Callable[[Exception], Result],
        after_commit: Callable[[list[Item]], None] | None = None,
    ) -> None:
        self._name = name
        self._database = database
        self._after_commit = after_commit
        self._decide = decide
        self._conflict = conflict
        self._unavailable = unavailable
        self.groups = 0
        """Transactions committed so far (diagnostics and tests)."""

    def write_group(self, group: list[Item]) -> list[Result]:
        """Decide and write the group; the answers, in order."""
        try:
            return self._transaction(group)
        except _ConflictError:
            if len(group) == 1:
                return [self._conflict(group[0])]
        return [result for item in group for result in self.write_group([item])]

    def _transaction(self, group: list[Item]) -> list[Result]:
        try:
            with self._database.session(write=True) as session:
                results = self._decide(session, group)
                session.commit()
        except IntegrityError as exc:
            raise _ConflictError from exc
        except Exception as exc:
            if not is_database_outage(exc):
                raise
            log.error("%s: a group of %d not stored: %s", self._name, len(group), exc)
            return [self._unavailable(exc)] * len(group)
        self.groups += 1
        if self._after_commit is not None:
            self._after_commit(group)
        return results


class GroupWriter(GroupTransaction[Item, Result]):
    """``await write(item)`` from any event loop: a ``GroupTransaction`` whose groups its own
    thread gathers (a ``GroupWorker``); ``stopping`` is the answer once ``shutdown`` has
    begun."""

    def __init__(
        self,
        name: str,
        database: Database,
        decide: Callable[[Session, list[Item]], list[Result]],
        *,
        conflict: Callable[[Item], Result],
        unavailable: Callable[[Exception], Result],
        stopping: Result,
        idle_s: float | None = None,
        after_pass: Callable[[], None] | None = None,
        after_commit: Callable[[list[Item]], None] | None = None,
        gather_gap_s: float = 0.0,
    ) -> None:
        super().__init__(
            name,
            database,
            decide,
            conflict=conflict,
            unavailable=unavailable,
            after_commit=after_commit,
        )
        self._stopping = stopping
        self._worker: GroupWorker[Item, Result] = GroupWorker(
            name,
            self.write_group,
            on_error=unavailable,
            idle_s=idle_s,
            after_pass=after_pass,
            gather_gap_s=gather_gap_s,
        )

    def start(self) -> None:
        self._worker.start()

    def shutdown(self) -> None:
        """Write what is queued, then stop the thread."""
        self._worker.shutdown()

    async def write(self, item: Item) -> Result:
        """Decide and write ``item`` with the others queued meanwhile; its answer."""
        try:
            future = self._worker.put(item)
        except StoppingError:
            return self._stopping
        # Shielded: a client that goes away does not un-write an item already queued.
        return await asyncio.shield(future)
