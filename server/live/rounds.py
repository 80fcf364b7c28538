"""The round watcher: long polls of ``GET /auctions/{id}/rounds/current`` and the pushes of the
round sockets.

However many agents wait on an auction, this process reads that auction's round from the
database once per ``WATCH_POLL_S`` while anyone waits (one asyncio task per watched auction),
and wakes every waiter when a round opens or the auction ends. Requests that do not wait share
the latest snapshot while it is younger than ``WATCH_POLL_S`` (the snapshots of ``MAX_WATCHED``
auctions are kept). A change this process makes itself (a cancel) is read at once (``poke``).
Waiters are bounded (``MAX_WAITERS`` per process; beyond that 503 with Retry-After).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Literal

from starlette.concurrency import run_in_threadpool

from server.store import crud
from server.store.db import Database
from server.store.status import AUCTION_UNFINISHED, RoundStatus
from server.store.tables import utcnow

log = logging.getLogger("srd.rounds")

WATCH_POLL_S = 0.05
"""How often a watched auction's round is read while agents wait on it, and the age below
which a snapshot is shared rather than read again."""
MAX_WAIT_S = 30.0
"""Longest ``?wait=`` a round request may ask for."""
MAX_WAITERS = 2048
"""Round requests waiting at once in one API process (beyond: 503)."""
MAX_WATCHED = 256
"""Auctions whose latest snapshot this process keeps (the idle ones beyond are forgotten)."""
PublishedStatus = Literal[RoundStatus.OPEN, RoundStatus.CLOSED, "none"]
"""A round as ``GET .../rounds/current`` shows it (none: no round has opened yet)."""


@dataclass(frozen=True)
class RoundSnapshot:
    """What this process last read of an auction's newest round."""

    head: crud.RoundHead
    body: crud.RoundBody | None
    """The round's rows, seeds and asked patrons (None when there is no round)."""

    @property
    def status(self) -> PublishedStatus:
        if self.head.status is None:
            return "none"
        return RoundStatus.OPEN if self.head.status == RoundStatus.OPEN else RoundStatus.CLOSED

    @property
    def auction_over(self) -> bool:
        return self.head.auction_status not in AUCTION_UNFINISHED

    def ready(self, after: int) -> bool:
        """Worth answering a long poll: a round above ``after`` is open, or the auction ended."""
        return self.auction_over or (
            self.status == RoundStatus.OPEN and (self.head.round or 0) > after
        )


@dataclass
class _Watch:
    """One watched auction: its latest snapshot, the read in flight, its waiters."""

    snapshot: RoundSnapshot | None = None
    read_at: float = -1.0
    reading: asyncio.Future[RoundSnapshot | None] | None = None
    changed: asyncio.Event = field(default_factory=asyncio.Event)
    waiters: int = 0
    poller: asyncio.Task[None] | None = None
    poked: asyncio.Event = field(default_factory=asyncio.Event)


@dataclass(frozen=True)
class Published:
    """One answer of the watcher: its JSON body and the snapshot it says."""

    body: bytes
    snapshot: RoundSnapshot

    @property
    def round(self) -> int | None:
        return self.snapshot.head.round

    @property
    def open(self) -> bool:
        """The round is open (its rows and seeds are in the body)."""
        return self.snapshot.status == RoundStatus.OPEN

    @property
    def auction_over(self) -> bool:
        return self.snapshot.auction_over

    def ready(self, after: int) -> bool:
        """Worth handing on to an agent that handled round ``after``."""
        return self.snapshot.ready(after)


class TooManyWaitersError(RuntimeError):
    """This process already holds ``MAX_WAITERS`` round requests."""


class RoundWatcher:
    """Long polls of ``GET /auctions/{id}/rounds/current`` (see the module docstring)."""

    def __init__(self, database: Database) -> None:
        self._database = database
        self._watches: dict[int, _Watch] = {}
        self._waiters = 0

    def poke(self, auction_id: int) -> None:
        """This process changed the auction: read it again now (its waiters hear at once)."""
        watch = self._watches.get(auction_id)
        if watch is not None:
            watch.read_at = -1.0
            watch.poked.set()

    async def current(self, auction_id: int, *, wait_s: float, after: int) -> bytes | None:
        """The answer body for the auction's newest round (None: no such auction), after up to
        ``wait_s`` seconds of waiting for a round above ``after`` to open."""
        published = await self.published(auction_id, wait_s=wait_s, after=after)
        return None if published is None else published.body

    async def published(self, auction_id: int, *, wait_s: float, after: int) -> Published | None:
        """``current`` with what the answer says (its round, open or not, the auction over)."""
        loop = asyncio.get_running_loop()
        watch = self._watches.setdefault(auction_id, _Watch())
        snapshot = await self._fresh(auction_id, watch, waits_after=after if wait_s > 0 else None)
        if snapshot is None:
            self._watches.pop(auction_id, None)
            return None
        give_up = loop.time() + min(wait_s, MAX_WAIT_S)
        while not snapshot.ready(after) and loop.time() < give_up:
            if self._waiters >= MAX_WAITERS:
                raise TooManyWaitersError(f"{MAX_WAITERS} round requests are waiting already")
            self._waiters += 1
            watch.waiters += 1
            if watch.poller is None or watch.poller.done():
                watch.poller = asyncio.create_task(self._poll(auction_id, watch))
            try:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(watch.changed.wait(), give_up - loop.time())
            finally:
                self._waiters -= 1
                watch.waiters -= 1
            if watch.snapshot is None:
                self._watches.pop(auction_id, None)
                return None
            snapshot = watch.snapshot
        body = _answer(auction_id, snapshot)
        self._forget_idle()
        return Published(body, snapshot)

    def _forget_idle(self) -> None:
        """Beyond ``MAX_WATCHED`` auctions, forget those nobody waits on, least recently read
        first (a forgotten auction's next request reads it afresh)."""
        if len(self._watches) <= MAX_WATCHED:
            return
        idle = sorted(
            (w.read_at, a) for a, w in self._watches.items() if w.waiters == 0 and w.reading is None
        )
        for _, auction_id in idle[: len(self._watches) - MAX_WATCHED]:
            del self._watches[auction_id]

    async def _fresh(
        self, auction_id: int, watch: _Watch, *, waits_after: int | None = None
    ) -> RoundSnapshot | None:
        """The snapshot, read again if older than ``WATCH_POLL_S`` (one read shared by all). A
        request that will wait for a round above ``waits_after`` (the snapshot has none) takes
        the snapshot of a watch whose poller runs, whatever its age: the poller reads it again
        soon anyway."""
        loop = asyncio.get_running_loop()
        polled = (
            waits_after is not None
            and watch.snapshot is not None
            and not watch.snapshot.ready(waits_after)
            and watch.poller is not None
            and not watch.poller.done()
        )
        if watch.snapshot is not None and (polled or loop.time() - watch.read_at < WATCH_POLL_S):
            return watch.snapshot
        if watch.reading is None:
            watch.reading = asyncio.ensure_future(self._read(auction_id, watch))
        return await asyncio.shield(watch.reading)

    async def _read(self, auction_id: int, watch: _Watch) -> RoundSnapshot | None:
        try:
            known = watch.snapshot
            snapshot = await run_in_threadpool(self._query, auction_id, known)
            watch.snapshot, watch.read_at = snapshot, asyncio.get_running_loop().time()
            if snapshot is None or known is None or _key(snapshot) != _key(known):
                watch.changed.set()
                watch.changed = asyncio.Event()
            return snapshot
        finally:
            watch.reading = None

    def _query(self, auction_id: int, known: RoundSnapshot | None) -> RoundSnapshot | None:
        with self._database.session(write=False) as session:
            head = crud.round_head(session, auction_id=auction_id)
            if head is None:
                return None
            if head.round_id is None:
                return RoundSnapshot(head, None)
            if known is not None and known.head.round_id == head.round_id:
                return RoundSnapshot(head, known.body)  # the rows of a round never change
            return RoundSnapshot(head, crud.round_body(session, round_id=head.round_id))

    async def _poll(self, auction_id: int, watch: _Watch) -> None:
        """Read the auction every ``WATCH_POLL_S`` (or when poked) while anyone waits on it."""
        try:
            while watch.waiters > 0:
                await self._fresh(auction_id, watch)
                watch.poked.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(watch.poked.wait(), WATCH_POLL_S)
        except Exception:  # a failed read wakes the waiters, who answer what they have
            log.exception("watching the rounds of auction %d failed", auction_id)
            watch.changed.set()
            watch.changed = asyncio.Event()

    async def close(self) -> None:
        """Stop the pollers (the waiters get their answers from the last snapshot)."""
        for watch in self._watches.values():
            if watch.poller is not None:
                watch.poller.cancel()
        self._watches.clear()


def _key(snapshot: RoundSnapshot) -> tuple[Any, ...]:
    head = snapshot.head
    return (head.auction_status, head.round_id, head.status)


def _answer(auction_id: int, snapshot: RoundSnapshot) -> bytes:
    """The JSON answer (see ``RoundPublic``)."""
    head, body = snapshot.head, snapshot.body
    is_open = snapshot.status == RoundStatus.OPEN and body is not None
    left = 0.0
    if is_open and head.deadline is not None:
        left = max(0.0, (head.deadline - utcnow()).total_seconds())
    answer: dict[str, Any] = {
        "auction_id": auction_id,
        "auction_status": head.auction_status,
        "fine_tune_mode": head.fine_tune_mode,
        "fine_tune_rounds": head.fine_tune_rounds,
        "round": head.round,
        "iteration": head.iteration,
        "status": snapshot.status,
        "deadline": None if head.deadline is None else _utc(head.deadline),
        "seconds_left": round(left, 3),
        "rows": body.rows if is_open and body is not None else None,
        "fine_tune_seed": None if body is None else body.fine_tune_seed,
        "augmentation_seed": None if body is None else body.augmentation_seed,
        "asked": body.asked if is_open and body is not None else [],
    }
    return json.dumps(answer, separators=(",", ":"), allow_nan=False).encode()


def _utc(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")
