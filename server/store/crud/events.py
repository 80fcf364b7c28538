"""What live updates read: a few columns of every watched row (one query for all the watched
auctions, one for all the watched jobs), then only the rounds that are new since the last read."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import Select, bindparam, select
from sqlalchemy.orm import Session

from server.store.crud.auctions import AUCTION_HISTORY, IterationFigures, bidder
from server.store.tables import (
    Auction,
    AuctionIteration,
    Job,
    ModelVersion,
    Participant,
    Purchase,
    Quit,
)


@dataclass(frozen=True)
class AuctionState:
    """Where an auction stands, as live updates read it."""

    status: str
    iteration: int
    price: float
    n_available: int
    n_initial: int
    stop_reason: str | None
    error: str | None
    finished_at: datetime | None
    fine_tune: bool
    fine_tune_mode: str
    fine_tune_rounds: int
    updated_at: datetime
    """Moves with every write to the auction, a fine-tuning round opening or closing included."""


@dataclass(frozen=True)
class PatronRef:
    """A patron by its model id, with the participant and version behind it."""

    model_id: int
    participant: str
    version: int
    version_id: int


@dataclass(frozen=True)
class RoundPurchase:
    patron: PatronRef
    price: float


@dataclass(frozen=True)
class AuctionRound(IterationFigures):
    """One committed iteration with the purchases and quits it made."""

    purchases: tuple[RoundPurchase, ...]
    quits: tuple[PatronRef, ...]


_AUCTION_STATES = select(
    Auction.id, *(getattr(Auction, f.name) for f in dataclasses.fields(AuctionState))
).where(Auction.id.in_(bindparam("ids", expanding=True)))
_ROUNDS = AUCTION_HISTORY.where(AuctionIteration.iteration >= bindparam("first")).where(
    AuctionIteration.iteration < bindparam("stop")
)


def _patrons_leaving(table: type[Purchase] | type[Quit], *extra: Any) -> Select[Any]:
    """(iteration, model id, participant, version, version id, *extra) of the patrons who
    bought (or quit) in the iterations first ≤ i < stop of an auction, in written order."""
    return (
        bidder(
            select(
                table.iteration,
                table.model_id,
                Participant.name,
                ModelVersion.version,
                ModelVersion.id,
                *extra,
            ),
            table,
        )
        .where(table.auction_id == bindparam("auction_id"))
        .where(table.iteration >= bindparam("first"))
        .where(table.iteration < bindparam("stop"))
        .order_by(table.id)
    )


_ROUND_PURCHASES = _patrons_leaving(Purchase, Purchase.price)
_ROUND_QUITS = _patrons_leaving(Quit)


def auction_states(session: Session, *, auction_ids: list[int]) -> dict[int, AuctionState]:
    """Where each of these auctions stands, by id (one query; a missing id is left out)."""
    rows = session.connection().execute(_AUCTION_STATES, {"ids": auction_ids})
    return {row[0]: AuctionState(*row[1:]) for row in rows}


def auction_state(session: Session, *, auction_id: int) -> AuctionState | None:
    """Where an auction stands (None: no such auction)."""
    return auction_states(session, auction_ids=[auction_id]).get(auction_id)


def auction_rounds(
    session: Session, *, auction_id: int, first: int, stop: int
) -> list[AuctionRound]:
    """Rounds ``first`` .. ``stop - 1`` of an auction with their purchases and quits, each
    patron named (three queries). Pass ``stop`` = the auction's committed ``iteration`` read
    before: a round is committed with its purchases and quits, so all of them are seen."""
    key = {"auction_id": auction_id, "first": first, "stop": stop}
    connection = session.connection()
    purchases: dict[int, list[RoundPurchase]] = {}
    for iteration, *patron, price in connection.execute(_ROUND_PURCHASES, key):
        purchases.setdefault(iteration, []).append(RoundPurchase(PatronRef(*patron), price))
    quits: dict[int, list[PatronRef]] = {}
    for iteration, *patron in connection.execute(_ROUND_QUITS, key):
        quits.setdefault(iteration, []).append(PatronRef(*patron))
    return [
        AuctionRound(
            **row._asdict(),
            purchases=tuple(purchases.get(row.iteration, ())),
            quits=tuple(quits.get(row.iteration, ())),
        )
        for row in connection.execute(_ROUNDS, key)
    ]


@dataclass(frozen=True)
class JobState:
    """Where a job stands, as live updates read it (the result is read once, at the end)."""

    status: str
    progress: float
    message: str
    attempt: int
    updated_at: datetime


_JOB_STATES = select(Job.id, *(getattr(Job, f.name) for f in dataclasses.fields(JobState))).where(
    Job.id.in_(bindparam("ids", expanding=True))
)


def job_states(session: Session, *, job_ids: list[int]) -> dict[int, JobState]:
    """Where each of these jobs stands, by id (one query; a missing id is left out)."""
    rows = session.connection().execute(_JOB_STATES, {"ids": job_ids})
    return {row[0]: JobState(*row[1:]) for row in rows}


def job_state(session: Session, *, job_id: int) -> JobState | None:
    """Where a job stands (None: no such job)."""
    return job_states(session, job_ids=[job_id]).get(job_id)
