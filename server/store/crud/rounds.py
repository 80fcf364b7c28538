"""Remote fine-tuning rounds as the round watcher polls them: the newest round of an auction,
and its body. (The worker opens and closes rounds itself, see
``server.auctions.steps``.)"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import bindparam, select
from sqlalchemy.orm import Session

from server.store.crud.auctions import AUCTION_PATRONS
from server.store.tables import Auction, FineTuneRound


@dataclass(frozen=True)
class RoundHead:
    """An auction's state and its newest fine-tuning round, as the round watcher polls them."""

    auction_status: str
    fine_tune_mode: str
    fine_tune_rounds: int
    round_id: int | None
    round: int | None
    iteration: int | None
    status: str | None
    deadline: datetime | None


_AUCTION_MODE = select(Auction.status, Auction.fine_tune_mode, Auction.fine_tune_rounds).where(
    Auction.id == bindparam("auction_id")
)
_NEWEST_ROUND = (
    select(
        FineTuneRound.id,
        FineTuneRound.round,
        FineTuneRound.iteration,
        FineTuneRound.status,
        FineTuneRound.deadline,
    )
    .where(FineTuneRound.auction_id == bindparam("auction_id"))
    .order_by(FineTuneRound.round.desc())
    .limit(1)
)


def round_head(session: Session, *, auction_id: int) -> RoundHead | None:
    """The auction's status and newest round (two small queries); None: no such auction."""
    key = {"auction_id": auction_id}
    connection = session.connection()
    auction = connection.execute(_AUCTION_MODE, key).one_or_none()
    if auction is None:
        return None
    newest = connection.execute(_NEWEST_ROUND, key).one_or_none()
    status, mode, rounds = auction
    if newest is None:
        return RoundHead(status, mode, rounds, None, None, None, None, None)
    return RoundHead(status, mode, rounds, newest.id, newest.round, newest.iteration,
                     newest.status, newest.deadline)  # fmt: skip


@dataclass(frozen=True)
class RoundBody:
    """What a round publishes beyond its head: the rows, the seeds, the patrons asked."""

    rows: list[list[float]]
    fine_tune_seed: int
    augmentation_seed: int
    asked: list[int]
    """Model ids (as in the auction's ``model_ids``) of the patrons asked."""


def round_body(session: Session, *, round_id: int) -> RoundBody:
    """A round's rows, seeds and asked patrons (two queries)."""
    connection = session.connection()
    row = connection.execute(
        select(
            FineTuneRound.auction_id,
            FineTuneRound.rows,
            FineTuneRound.fine_tune_seed,
            FineTuneRound.augmentation_seed,
            FineTuneRound.asked,
        ).where(FineTuneRound.id == round_id)
    ).one()
    model_ids = list(connection.scalars(AUCTION_PATRONS, {"auction_id": row.auction_id}))
    return RoundBody(
        row.rows,
        row.fine_tune_seed,
        row.augmentation_seed,
        [model_ids[position] for position in row.asked],
    )
