"""A vote's explanation: one committed iteration's stored neurons of one patron."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.store.tables import Auction, AuctionIteration, ModelVersion, Participant


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


def model_name(session: Session, *, model_id: int) -> tuple[str, int] | None:
    """The participant and version of a model id."""
    row = (
        session.connection()
        .execute(
            select(Participant.name, ModelVersion.version)
            .join(ModelVersion.participant)
            .where(ModelVersion.id == model_id)
        )
        .one_or_none()
    )
    return (row[0], row[1]) if row is not None else None
