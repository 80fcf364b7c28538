"""Remote fine-tuning rounds as live updates read them: the newest round of an auction, and its
body. (The worker opens and closes rounds itself, see
``server.auctions.steps``.)"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import Connection, bindparam, select
from sqlalchemy.orm import Session

from server.store.crud.auctions import AUCTION_PATRONS
from server.store.tables import AuctionPatron, FineTuneRound, ModelVersion, Participant


@dataclass(frozen=True)
class RoundHead:
    """An auction's newest fine-tuning round, as live updates read it."""

    round_id: int
    round: int
    iteration: int
    status: str
    deadline: datetime


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
    """The auction's newest round (one query); None: no round has opened yet."""
    newest = session.connection().execute(_NEWEST_ROUND, {"auction_id": auction_id}).one_or_none()
    return None if newest is None else RoundHead(*newest)


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


_PATRON_TOKENS = (
    select(Participant.token_hash)
    .join(ModelVersion, ModelVersion.participant_id == Participant.id)
    .join(AuctionPatron, AuctionPatron.model_id == ModelVersion.id)
    .where(AuctionPatron.auction_id == bindparam("auction_id"))
)


def patron_tokens(connection: Connection, *, auction_id: int) -> frozenset[str]:
    """The token hashes of the participants with a patron in the auction."""
    return frozenset(connection.scalars(_PATRON_TOKENS, {"auction_id": auction_id}))
