"""A vote's explanation: one committed iteration's stored neurons of one patron."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.store.tables import (
    Auction,
    AuctionIteration,
    AuctionPatron,
    FineTuneAnswer,
    FineTuneRound,
    ModelVersion,
    Participant,
)


@dataclass(frozen=True)
class IterationVotes:
    """What a committed iteration kept of its votes: ``explanations`` is null for iterations
    committed before explanations were kept."""

    explanations: dict[str, Any] | None


def iteration_votes(
    session: Session, *, auction_id: int, iteration: int
) -> tuple[bool, IterationVotes | None]:
    """Whether the auction exists, and its committed ``iteration`` (None if not committed)."""
    connection = session.connection()
    exists = connection.scalar(select(Auction.id).where(Auction.id == auction_id)) is not None
    if not exists:
        return False, None
    row = connection.execute(
        select(AuctionIteration.explanations).where(
            AuctionIteration.auction_id == auction_id, AuctionIteration.iteration == iteration
        )
    ).one_or_none()
    return True, IterationVotes(*row) if row is not None else None


def bidding_version(
    session: Session, *, auction_id: int, model_id: int, iteration: int
) -> tuple[str, int] | None:
    """The participant and version of the patron that entered the auction as ``model_id``,
    as it bid in ``iteration``: the version its last remote round before that iteration left
    it with (each round's answer names it), else the one it entered with. None: not a patron."""
    connection = session.connection()
    position = connection.scalar(
        select(AuctionPatron.position).where(
            AuctionPatron.auction_id == auction_id, AuctionPatron.model_id == model_id
        )
    )
    if position is None:
        return None
    after_rounds = connection.scalar(
        select(FineTuneAnswer.model_id)
        .join(FineTuneRound, FineTuneRound.id == FineTuneAnswer.round_id)
        .where(
            FineTuneRound.auction_id == auction_id,
            FineTuneRound.iteration < iteration,
            FineTuneAnswer.position == position,
        )
        .order_by(FineTuneRound.round.desc())
        .limit(1)
    )
    row = connection.execute(
        select(Participant.name, ModelVersion.version)
        .join(ModelVersion.participant)
        .where(ModelVersion.id == (after_rounds or model_id))
    ).one()
    return row[0], row[1]
