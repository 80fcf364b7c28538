"""The round watcher: long polls of ``GET /auctions/{id}/rounds/current``.

However many agents wait on an auction, this process reads that auction's round from the
database once per wake-up: one asyncio task per watched auction reads it while anyone waits,
whenever this process's doorbell rings (its auction workers ring it after every commit,
``server.doorbell``) and at the bell's fallback period otherwise (every ``WATCH_POLL_S``
without a bell), and wakes every waiter when a round opens or the auction ends. Requests that
do not wait share the latest snapshot while it is younger than ``WATCH_POLL_S`` (the snapshots of
``MAX_WATCHED`` auctions are kept). The answer body of a round is built once (its 64 × 8 rows
serialised once) and shared by all its waiters; only ``seconds_left`` is written per answer.
Waiters are bounded (``MAX_WAITERS`` per process; beyond that 503 with Retry-After). The bytes
of the answers that carry a round are counted (``PublishedBytes``) and added to the round's
``bytes_published``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Literal

from starlette.concurrency import run_in_threadpool

from server import crud, doorbell
from server.db import Database
from server.models import utcnow
from server.remote_rounds.writer import PublishedBytes
from server.status import AUCTION_UNFINISHED, RoundStatus

log = logging.getLogger("srd.rounds")

WATCH_POLL_S = 0.004
"""The age below which a snapshot is shared rather than read again; without a doorbell, also
how often a watched auction's round is read while agents wait on it."""
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
    read_ring: int = -1
    """The watcher's ring count when the snapshot's read began (a later ring: read again)."""
    template: tuple[int | None, str, bytes, bytes] | None = None
    """(round id, status, body before and after ``seconds_left``) of the last answer built."""


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


RoundSeen = Callable[[int, int | None, str, Sequence[int]], None]
"""Told (auction id, round, status, asked model ids) whenever the watcher reads a change in an
auction's newest round (``UploadLookup.round_seen``)."""


class TooManyWaitersError(RuntimeError):
    """This process already holds ``MAX_WAITERS`` round requests."""


class RoundWatcher:
    """Long polls of ``GET /auctions/{id}/rounds/current`` (see the module docstring)."""

    def __init__(
        self, database: Database, published: PublishedBytes, *, on_round: RoundSeen | None = None
    ) -> None:
        self._database = database
        self._published = published
        self._on_round = on_round
        self._watches: dict[int, _Watch] = {}
        self._waiters = 0
        self._bell: doorbell.Bell | None = None
        self._bell_tried = False
        self._rings = 0
        self._rung = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None

    def _listen(self) -> None:
        """Bind this process's watch bell, rung by its auction workers after every commit, and
        read it on the running event loop (done on a loop's first round request)."""
        loop = asyncio.get_running_loop()
        if self._loop is loop:
            return
        if self._loop is not None and self._bell is not None:
            with contextlib.suppress(RuntimeError, ValueError):
                self._loop.remove_reader(self._bell.fileno())
        self._loop, self._rung = loop, asyncio.Event()
        if not self._bell_tried:
            self._bell_tried = True
            self._bell = doorbell.listen(
                doorbell.scope(self._database.url), doorbell.watch_bell(os.getpid())
            )
        if self._bell is not None:
            loop.add_reader(self._bell.fileno(), self._on_ring)

    def _on_ring(self) -> None:
        if self._bell is not None and self._bell.drain():
            self._rang()

    def _rang(self) -> None:
        self._rings += 1
        self._rung.set()
        self._rung = asyncio.Event()

    def wake(self) -> None:
        """Read the watched auctions again now, as on a ring: for a change this process
        committed itself (a cancelled auction), which no worker rings for. Any thread."""
        if self._loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop has closed: nobody waits
                self._loop.call_soon_threadsafe(self._rang)

    async def _pause(self) -> None:
        """Until the bell rings, or the fallback period passes (without a bell: a short poll)."""
        if self._bell is None:
            await asyncio.sleep(WATCH_POLL_S)
            return
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._rung.wait(), doorbell.FALLBACK_S)

    async def current(self, auction_id: int, *, wait_s: float, after: int) -> bytes | None:
        """The answer body for the auction's newest round (None: no such auction), after up to
        ``wait_s`` seconds of waiting for a round above ``after`` to open."""
        published = await self.published(auction_id, wait_s=wait_s, after=after)
        return None if published is None else published.body

    async def published(self, auction_id: int, *, wait_s: float, after: int) -> Published | None:
        """``current`` with what the answer says (its round, open or not, the auction over)."""
        loop = asyncio.get_running_loop()
        self._listen()
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
        body = self._answer(auction_id, watch, snapshot)
        if snapshot.head.round_id is not None:
            self._published.count(snapshot.head.round_id, len(body))
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
        """The snapshot, read again if older than ``WATCH_POLL_S`` or the bell rang since its
        read began (one read shared by all). A request that will wait for a round above
        ``waits_after`` (the snapshot has none) takes the snapshot of a watch whose poller
        runs, whatever its age, while the bell has not rung: the poller reads it again at
        the bell's fallback period anyway, and the agents that go back to waiting right after
        a round was pushed to them cost no read."""
        loop = asyncio.get_running_loop()
        polled = (
            waits_after is not None
            and watch.snapshot is not None
            and not watch.snapshot.ready(waits_after)
            and watch.poller is not None
            and not watch.poller.done()
        )
        if (
            watch.snapshot is not None
            and (polled or loop.time() - watch.read_at < WATCH_POLL_S)
            and watch.read_ring == self._rings
        ):
            return watch.snapshot
        if watch.reading is None:
            watch.reading = asyncio.ensure_future(self._read(auction_id, watch))
        return await asyncio.shield(watch.reading)

    async def _read(self, auction_id: int, watch: _Watch) -> RoundSnapshot | None:
        try:
            known, rings = watch.snapshot, self._rings
            snapshot = await run_in_threadpool(self._query, auction_id, known)
            watch.snapshot, watch.read_at = snapshot, asyncio.get_running_loop().time()
            watch.read_ring = rings
            if snapshot is None or known is None or _key(snapshot) != _key(known):
                watch.changed.set()
                watch.changed = asyncio.Event()
                if snapshot is not None and self._on_round is not None:
                    body = snapshot.body
                    asked = [] if body is None else body.asked
                    self._on_round(auction_id, snapshot.head.round, snapshot.status, asked)
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
        """Read the auction again whenever the bell rings (and at its fallback period) while
        anyone waits on it."""
        try:
            while watch.waiters > 0:
                await self._fresh(auction_id, watch)
                await self._pause()
        except Exception:  # a failed read wakes the waiters, who answer what they have
            log.exception("watching the rounds of auction %d failed", auction_id)
            watch.changed.set()
            watch.changed = asyncio.Event()

    def _answer(self, auction_id: int, watch: _Watch, snapshot: RoundSnapshot) -> bytes:
        """The JSON answer (see ``RoundPublic``): built once per round and status."""
        head = snapshot.head
        status = snapshot.status
        if watch.template is None or watch.template[:2] != (head.round_id, status):
            before, after = _template(auction_id, snapshot)
            watch.template = (head.round_id, status, before, after)
        _, _, before, after = watch.template
        left = 0.0
        if status == RoundStatus.OPEN and head.deadline is not None:
            left = max(0.0, (head.deadline - utcnow()).total_seconds())
        return before + json.dumps(round(left, 3)).encode() + after

    async def close(self) -> None:
        """Stop the pollers (the waiters get their answers from the last snapshot)."""
        for watch in self._watches.values():
            if watch.poller is not None:
                watch.poller.cancel()
        self._watches.clear()
        if self._bell is not None:
            if self._loop is not None:
                with contextlib.suppress(RuntimeError, ValueError):
                    self._loop.remove_reader(self._bell.fileno())
            self._bell.close()
            self._bell = None
        self._loop, self._bell_tried = None, False


def _key(snapshot: RoundSnapshot) -> tuple[Any, ...]:
    head = snapshot.head
    return (head.auction_status, head.round_id, head.status)


_SECONDS_LEFT = "\x00seconds_left\x00"


def _template(auction_id: int, snapshot: RoundSnapshot) -> tuple[bytes, bytes]:
    """The answer's bytes before and after its ``seconds_left`` value."""
    head, body = snapshot.head, snapshot.body
    is_open = snapshot.status == RoundStatus.OPEN and body is not None
    answer: dict[str, Any] = {
        "auction_id": auction_id,
        "auction_status": head.auction_status,
        "fine_tune_mode": head.fine_tune_mode,
        "fine_tune_rounds": head.fine_tune_rounds,
        "round": head.round,
        "iteration": head.iteration,
        "status": snapshot.status,
        "deadline": None if head.deadline is None else _utc(head.deadline),
        "seconds_left": _SECONDS_LEFT,
        "rows": body.rows if is_open and body is not None else None,
        "fine_tune_seed": None if body is None else body.fine_tune_seed,
        "augmentation_seed": None if body is None else body.augmentation_seed,
        "asked": body.asked if is_open and body is not None else [],
    }
    text = json.dumps(answer, separators=(",", ":"), allow_nan=False)
    before, after = text.split(json.dumps(_SECONDS_LEFT))
    return before.encode(), after.encode()


def _utc(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")
