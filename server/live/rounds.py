"""The rounds' share of live updates: long polls of ``GET /auctions/{id}/rounds/current`` and
the pushes of the round sockets.

They listen to this process's live-update source (``server.live.source``): however many agents
wait on an auction, its newest round is read once per change and every waiter wakes. A request
that does not wait takes the snapshot of an auction already watched, or reads it (one read
shared by the requests that arrive meanwhile). Waiters are bounded per process, the auction's
patrons (``MAX_WAITERS``) apart from anyone else (``MAX_WATCHER_WAITERS``); beyond, 503 with
Retry-After.
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import dataclass
from datetime import datetime
from typing import Any, Literal

from sqlalchemy.orm import Session

from server.live.source import LiveSource
from server.store import crud
from server.store.status import AUCTION_UNFINISHED, RoundStatus
from server.store.tables import utcnow

MAX_WAIT_S = 30.0
"""Longest ``?wait=`` a round request may ask for."""
MAX_WAITERS = 2048
"""Round requests of patrons (a participant token with a model in the auction) waiting at
once in one API process (beyond: 503)."""
MAX_WATCHER_WAITERS = 512
"""The same for anyone else (no token, or not the auction's): apart from the patrons', so that
watchers, or many addresses each within its share, cannot take theirs."""
PublishedStatus = Literal[RoundStatus.OPEN, RoundStatus.CLOSED, "none"]
"""A round as ``GET .../rounds/current`` shows it (none: no round has opened yet)."""


def _published_status(head: crud.RoundHead | None) -> PublishedStatus:
    if head is None:
        return "none"
    return RoundStatus.OPEN if head.status == RoundStatus.OPEN else RoundStatus.CLOSED


@dataclass(frozen=True)
class RoundSnapshot:
    """An auction and its newest round, as this process last read them."""

    state: crud.AuctionState
    head: crud.RoundHead | None
    """The newest round (None when no round has opened yet)."""
    body: crud.RoundBody | None
    """The newest round's rows, seeds and asked patrons."""
    answer: AnswerJson
    """Its JSON answer, built once for every request and push that hands it on."""

    @property
    def status(self) -> PublishedStatus:
        return _published_status(self.head)

    @property
    def auction_over(self) -> bool:
        return self.state.status not in AUCTION_UNFINISHED

    def ready(self, after: int) -> bool:
        """Worth answering a long poll: a round above ``after`` is open, or the auction ended."""
        return self.auction_over or (
            self.head is not None and self.status == RoundStatus.OPEN and self.head.round > after
        )


def round_view(
    session: Session,
    auction_id: int,
    state: crud.AuctionState | None,
    previous: RoundSnapshot | None,
) -> RoundSnapshot | None:
    """What the rounds show of an auction (None: no such auction)."""
    if state is None:
        return None
    head = crud.round_head(session, auction_id=auction_id)
    if head is None:
        body = None
    elif (
        previous is not None
        and previous.head is not None
        and previous.head.round_id == head.round_id
    ):
        body = previous.body  # the rows of a round never change
    else:
        body = crud.round_body(session, round_id=head.round_id)
    return RoundSnapshot(state, head, body, _answer_json(auction_id, state, head, body))


@dataclass(frozen=True)
class Published:
    """One answer of the watcher: its JSON body and the snapshot it says."""

    body: bytes
    snapshot: RoundSnapshot

    @property
    def round(self) -> int | None:
        return None if self.snapshot.head is None else self.snapshot.head.round

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
    """This process already holds its most waiting round requests of that kind."""


class RoundWatcher:
    """Long polls of ``GET /auctions/{id}/rounds/current`` (see the module docstring)."""

    def __init__(self, source: LiveSource) -> None:
        self._source = source
        self._waiters = {True: 0, False: 0}  # patrons' (True) and others

    @property
    def draining(self) -> bool:
        """The server is shutting down (waits end at once)."""
        return self._source.draining

    def poke(self, auction_id: int) -> None:
        """This process changed the auction: read it again now (its waiters hear at once)."""
        self._source.poke("auction", auction_id)

    async def current(
        self, auction_id: int, *, wait_s: float, after: int, patron: bool = False
    ) -> bytes | None:
        """The answer body for the auction's newest round (None: no such auction), after up to
        ``wait_s`` seconds of waiting for a round above ``after`` to open."""
        published = await self.published(auction_id, wait_s=wait_s, after=after, patron=patron)
        return None if published is None else published.body

    async def published(
        self, auction_id: int, *, wait_s: float, after: int, patron: bool = False
    ) -> Published | None:
        """``current`` with what the answer says (its round, open or not, the auction over);
        a wait counts against the patrons' bound or the others'."""
        most = MAX_WAITERS if patron else MAX_WATCHER_WAITERS
        loop = asyncio.get_running_loop()
        give_up = loop.time() + min(wait_s, MAX_WAIT_S)
        async with self._source.watch("auction", auction_id, round_view) as feed:
            while True:
                feed.raise_failure()  # the last read failed (an outage): 503, not the snapshot
                generation, snapshot = feed.generation, feed.snapshot
                if snapshot is None:
                    return None
                if snapshot.ready(after) or loop.time() >= give_up or self._source.draining:
                    break
                if self._waiters[patron] >= most:
                    whose = "patrons'" if patron else "watchers' (no patron's token)"
                    raise TooManyWaitersError(f"{most} {whose} round requests are waiting already")
                self._waiters[patron] += 1
                try:
                    await feed.wait(generation, give_up - loop.time())
                finally:
                    self._waiters[patron] -= 1
        return Published(snapshot.answer.body(), snapshot)


@dataclass(frozen=True)
class AnswerJson:
    """A snapshot's JSON answer (see ``RoundPublic``), split around ``seconds_left``, the one
    field that moves between two requests for the same snapshot."""

    before: bytes
    after: bytes
    deadline: datetime | None
    """The open round's deadline (None: ``seconds_left`` is 0)."""

    def body(self) -> bytes:
        """The answer's bytes, ``seconds_left`` counted now."""
        left = 0.0 if self.deadline is None else (self.deadline - utcnow()).total_seconds()
        return b"%s%s%s" % (self.before, json.dumps(round(max(0.0, left), 3)).encode(), self.after)


def _answer_json(
    auction_id: int,
    state: crud.AuctionState,
    head: crud.RoundHead | None,
    body: crud.RoundBody | None,
) -> AnswerJson:
    status = _published_status(head)
    is_open = status == RoundStatus.OPEN and body is not None
    before: dict[str, Any] = {
        "auction_id": auction_id,
        "auction_status": state.status,
        "fine_tune_mode": state.fine_tune_mode,
        "fine_tune_rounds": state.fine_tune_rounds if state.fine_tune else None,
        "round": None if head is None else head.round,
        "iteration": None if head is None else head.iteration,
        "status": status,
        "deadline": None if head is None else _utc(head.deadline),
    }
    after: dict[str, Any] = {
        "rows": body.rows if is_open and body is not None else None,
        "fine_tune_seed": None if body is None else body.fine_tune_seed,
        "augmentation_seed": None if body is None else body.augmentation_seed,
        "asked": body.asked if is_open and body is not None else [],
    }
    return AnswerJson(
        _dumps(before)[:-1] + b',"seconds_left":',
        b"," + _dumps(after)[1:],
        head.deadline if is_open and head is not None else None,
    )


def _dumps(value: dict[str, Any]) -> bytes:
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode()


def _utc(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")
