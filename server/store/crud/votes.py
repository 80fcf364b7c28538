"""A vote's explanation: one committed iteration's stored neurons of one patron."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.store.tables import (
    Auction,
    AuctionIteration,
    AuctionPatron,
    FineTuneAnswer,
    FineTuneRound,
    ModelVersion,
    Participant,
    TunedWeights,
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


@dataclass(frozen=True)
class Bidder:
    """A patron as it bid in one iteration: its participant, the version that bid, and the
    iteration after which a server-mode auction last fine-tuned that version's weights inside
    the market (None: it bid with the version's own weights)."""

    participant: str
    version: int
    version_id: int
    fine_tuned_after: int | None
    weights_kept: bool
    """False when the market had fine-tuned this auction's patrons before the iteration but
    did not keep the weights (an auction created before the server kept them)."""


def bidders(
    session: Session, *, auction_id: int, iteration: int, only: int | None = None
) -> dict[int, Bidder]:
    """Every patron of an auction (by the model id it entered with; only the patron ``only``
    if given) as it bid in ``iteration``: with the version its last remote round before that
    iteration left it (each round's answer names it), else the one it entered with, and
    whether the market had fine-tuned it since (four queries, five for an auction from before
    fine-tuned weights were kept)."""
    connection = session.connection()
    patron = AuctionPatron.auction_id == auction_id
    if only is not None:
        patron = patron & (AuctionPatron.model_id == only)
    last_round = (
        select(
            FineTuneAnswer.position,
            FineTuneAnswer.model_id,
            func.row_number()
            .over(partition_by=FineTuneAnswer.position, order_by=FineTuneRound.round.desc())
            .label("newest"),
        )
        .join(FineTuneRound, FineTuneRound.id == FineTuneAnswer.round_id)
        .where(FineTuneRound.auction_id == auction_id, FineTuneRound.iteration < iteration)
        .subquery()
    )
    bid_with = func.coalesce(last_round.c.model_id, AuctionPatron.model_id)
    rows = connection.execute(
        select(AuctionPatron.model_id, Participant.name, ModelVersion.version, ModelVersion.id)
        .outerjoin(
            last_round,
            (last_round.c.position == AuctionPatron.position) & (last_round.c.newest == 1),
        )
        .join(ModelVersion, ModelVersion.id == bid_with)
        .join(Participant, Participant.id == ModelVersion.participant_id)
        .where(patron)
    )
    fine_tune, mode, rounds, kept = connection.execute(
        select(
            Auction.fine_tune,
            Auction.fine_tune_mode,
            Auction.fine_tune_rounds,
            Auction.keeps_tuned_weights,
        ).where(Auction.id == auction_id)
    ).one()
    tuned: dict[int, int] = {
        patron: after
        for patron, after in connection.execute(
            select(TunedWeights.model_id, func.max(TunedWeights.iteration))
            .where(
                TunedWeights.auction_id == auction_id,
                TunedWeights.iteration < iteration,
                TunedWeights.kept,
                *(() if only is None else (TunedWeights.model_id == only,)),
            )
            .group_by(TunedWeights.model_id)
        )
    }
    unknown: set[int] = set()
    if not kept and fine_tune and mode == "server" and min(iteration, rounds) > 0:
        # Created before fine-tuned weights were kept: a patron that fine-tunes bid with
        # weights no longer known, unless a kept row (written since) holds them.
        epochs = ModelVersion.manifest["fine_tuning"]["epochs"].as_integer()
        unknown = set(
            connection.scalars(
                select(AuctionPatron.model_id)
                .join(ModelVersion, ModelVersion.id == AuctionPatron.model_id)
                .where(patron, epochs > 0)
            )
        ).difference(tuned)
    return {
        model_id: Bidder(name, version, version_id, tuned.get(model_id), model_id not in unknown)
        for model_id, name, version, version_id in rows
    }


def bid_manifest(
    session: Session,
    *,
    auction_id: int,
    model_id: int,
    version_id: int,
    fine_tuned_after: int | None,
) -> dict[str, Any]:
    """The weights that patron ``model_id`` bid with (as ``bidders`` names them): those the
    market fine-tuned after ``fine_tuned_after``, else version ``version_id``'s."""
    connection = session.connection()
    if fine_tuned_after is None:
        found = connection.scalar(
            select(ModelVersion.manifest).where(ModelVersion.id == version_id)
        )
    else:
        found = connection.scalar(
            select(TunedWeights.manifest).where(
                TunedWeights.auction_id == auction_id,
                TunedWeights.model_id == model_id,
                TunedWeights.iteration == fine_tuned_after,
            )
        )
    assert isinstance(found, dict)
    return found


def fine_tunings(
    session: Session, *, auction_id: int, model_id: int, iteration: int
) -> list[tuple[int, bool, list[dict[str, str]]]]:
    """Patron ``model_id``'s fine-tunings inside the market before ``iteration``: (the
    iteration after which, whether its re-screening kept it, the screener's reasons when it
    did not: none stored before they were kept), in order."""
    rows = session.connection().execute(
        select(TunedWeights.iteration, TunedWeights.kept, TunedWeights.reasons)
        .where(
            TunedWeights.auction_id == auction_id,
            TunedWeights.model_id == model_id,
            TunedWeights.iteration < iteration,
        )
        .order_by(TunedWeights.iteration)
    )
    return [(after, kept, reasons or []) for after, kept, reasons in rows]
