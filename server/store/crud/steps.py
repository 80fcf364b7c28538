"""The statements of an auction's steps (``server.auctions.steps``): read where the auction
stands, start it, commit an iteration with the round it opens, close a round. Every write is
conditional on the auction standing where the step found it (``MovedOnError`` otherwise)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Connection, bindparam, func, insert, select, update
from sqlalchemy.orm import Session, selectinload, undefer

from server.store.crud.auctions import IterationFigures
from server.store.crud.live import notify_change
from server.store.db import JSONText
from server.store.status import (
    ANSWERED,
    AUCTION_UNFINISHED,
    AnswerOutcome,
    AuctionStatus,
    RoundStatus,
)
from server.store.tables import (
    Auction,
    AuctionIteration,
    AuctionPatron,
    FineTuneAnswer,
    FineTuneRound,
    ModelVersion,
    Purchase,
    Quit,
    TunedWeights,
)

CLOSE_GRACE = timedelta(seconds=0.5)
"""A round left open after its deadline is closed this much later: an upload whose last byte
arrived before the deadline (its arrival is what counts) may still be on its way to the
database then, and would find the round closed."""


class MovedOnError(RuntimeError):
    """The auction is no longer where the step found it (cancelled, or moved by another)."""


class PendingUploadsError(RuntimeError):
    """An upload of the round being closed still awaits its verdict."""


@dataclass(frozen=True)
class StepRound:
    """What a step needs of an auction's newest fine-tuning round."""

    id: int
    round: int
    asked: list[int]
    """Positions of the patrons asked."""
    deadline: datetime
    open: bool


@dataclass(frozen=True)
class IterationRow(IterationFigures):
    """One played iteration, in the database's terms (patrons by model id)."""

    finished: bool
    stop_reason: str | None
    explanations: dict[str, Any] | JSONText | None
    """The patrons' explained votes (``JSONText``: encoded before the write transaction)."""
    buyers: list[tuple[int, float]]
    """(model id, price) of each purchase."""
    quitters: list[int]
    tuned: list[tuple[int, JSONText]] = field(default_factory=list)
    """(model id, manifest) of each patron a server-mode auction fine-tuned after this
    iteration and kept (its weights from the next iteration on)."""
    refused: list[tuple[int, list[dict[str, str]]]] = field(default_factory=list)
    """(model id, the screener's reasons) of each patron whose fine-tuning after this
    iteration the re-screening refused (it bid on with the weights it had)."""


@dataclass(frozen=True)
class NewRound:
    """A fine-tuning round an iteration opens."""

    round: int
    iteration: int
    rows: list[list[float]]
    fine_tune_seed: int
    augmentation_seed: int
    asked: list[int]
    deadline: datetime


def step_state(session: Session, *, auction_id: int) -> tuple[Auction, StepRound | None] | None:
    """The auction (checkpoint and patrons loaded) and its newest round; None for an auction
    that is gone."""
    auction = session.scalars(
        select(Auction)
        .where(Auction.id == auction_id)
        .options(undefer(Auction.checkpoint), selectinload(Auction.patrons))
    ).one_or_none()
    if auction is None:
        return None
    row = session.scalars(
        select(FineTuneRound)
        .where(FineTuneRound.auction_id == auction_id)
        .order_by(FineTuneRound.round.desc())
        .limit(1)
    ).one_or_none()
    if row is None:
        return auction, None
    is_open = row.status == RoundStatus.OPEN
    return auction, StepRound(row.id, row.round, list(row.asked), row.deadline, is_open)


def patron_manifests(session: Session, *, model_ids: Sequence[int]) -> list[dict[str, Any]]:
    """The stored manifests of these versions, in order."""
    rows = session.execute(
        select(ModelVersion.id, ModelVersion.manifest).where(ModelVersion.id.in_(model_ids))
    )
    by_id: dict[int, dict[str, Any]] = {model_id: manifest for model_id, manifest in rows}
    return [by_id[model_id] for model_id in model_ids]


def answered(session: Session, *, round_id: int) -> int:
    """How many asked patrons have answered the round (pending uploads included)."""
    return session.execute(
        select(func.count())
        .select_from(FineTuneAnswer)
        .where(FineTuneAnswer.round_id == round_id, FineTuneAnswer.outcome.in_(ANSWERED))
    ).scalar_one()


def due_at(session: Session, *, auction_id: int, when: datetime) -> None:
    """The pending or running auction's next step is due at ``when``."""
    session.execute(
        update(Auction)
        .where(Auction.id == auction_id, Auction.status.in_(AUCTION_UNFINISHED))
        .values(next_step_at=when)
    )


def push_back_deadlines(
    session: Session, *, began: datetime, now: datetime, retry: timedelta
) -> tuple[list[int], list[int]]:
    """Give the open rounds of running auctions the time an outage took from them: a round
    with time left at ``began`` (the outage's start, at the earliest) gets that time again
    from ``now`` (its end), at most its auction's whole ``round_deadline_s``, plus ``retry``
    (the clients the outage refused were told to try again that much later), never less than
    it has; the auction's step is then due at the new deadline. A round given time back
    since ``began`` (by another replica that met the same outage) is left as it is. The
    auctions whose round moved (announced to live updates), and those already given back."""
    rows = session.execute(
        select(FineTuneRound.id, FineTuneRound.auction_id, FineTuneRound.deadline)
        .add_columns(FineTuneRound.given_back_at, Auction.round_deadline_s)
        .join(Auction, Auction.id == FineTuneRound.auction_id)
        .where(FineTuneRound.status == RoundStatus.OPEN, FineTuneRound.deadline > began)
        .where(Auction.status == AuctionStatus.RUNNING)
        .order_by(FineTuneRound.id)  # one lock order for every pusher (replicas: no deadlock)
        .with_for_update(of=FineTuneRound)
    ).all()
    moved: list[int] = []
    already: list[int] = []
    for round_id, auction_id, deadline, given_back_at, whole_s in rows:
        if given_back_at is not None and given_back_at >= began:
            already.append(auction_id)
            continue
        pushed = now + min(timedelta(seconds=whole_s), deadline - began) + retry
        if pushed <= deadline:
            continue
        session.execute(
            update(FineTuneRound)
            .where(FineTuneRound.id == round_id, FineTuneRound.status == RoundStatus.OPEN)
            .values(deadline=pushed, given_back_at=now)
        )
        session.execute(
            update(Auction)
            .where(Auction.id == auction_id, Auction.status == AuctionStatus.RUNNING)
            .values(next_step_at=pushed + CLOSE_GRACE, updated_at=now)
        )
        notify_change(session, kind="auction", row_id=auction_id)
        moved.append(auction_id)
    return moved, already


def start(session: Session, *, auction_id: int, finished: bool, now: datetime) -> None:
    """A pending auction running from ``now`` (finished at once if ``finished``)."""
    values: dict[str, object] = {
        "status": AuctionStatus.RUNNING,
        "started_at": now,
        "updated_at": now,
    }
    if finished:
        values.update(status=AuctionStatus.FINISHED, finished_at=now, next_step_at=None)
    started = session.execute(
        update(Auction)
        .where(Auction.id == auction_id, Auction.status == AuctionStatus.PENDING)
        .values(**values)
    )
    if started.rowcount != 1:  # type: ignore[attr-defined]
        raise MovedOnError(auction_id)
    notify_change(session, kind="auction", row_id=auction_id)


def commit_iteration(
    session: Session,
    *,
    auction_id: int,
    row: IterationRow,
    checkpoint: bytes,
    opened: NewRound | None,
    now: datetime,
) -> StepRound | None:
    """Write one iteration played at ``now``: its row, purchases and quits, the new price and
    supply, the checkpoint, the round it opens (returned) and when the next step is due (now
    while it plays, the round's deadline plus ``CLOSE_GRACE``, never once ended)."""
    due = None if row.finished else (opened.deadline + CLOSE_GRACE if opened is not None else now)
    moved = session.execute(
        update(Auction)
        .where(
            Auction.id == auction_id,
            Auction.iteration == row.iteration,
            Auction.status == AuctionStatus.RUNNING,
        )
        .values(
            iteration=row.iteration + 1,
            price=row.next_price,
            n_available=row.n_available_after,
            checkpoint=checkpoint,
            status=AuctionStatus.FINISHED if row.finished else AuctionStatus.RUNNING,
            stop_reason=row.stop_reason,
            finished_at=now if row.finished else None,
            updated_at=now,
            next_step_at=due,
        )
    )
    if moved.rowcount != 1:  # type: ignore[attr-defined]
        raise MovedOnError(auction_id)
    notify_change(session, kind="auction", row_id=auction_id)
    connection = session.connection()
    connection.execute(
        insert(AuctionIteration),
        {
            "auction_id": auction_id,
            "iteration": row.iteration,
            "price": row.price,
            "n_available": row.n_available,
            "votes": row.votes,
            "row_votes": row.row_votes,
            "next_price": row.next_price,
            "n_available_after": row.n_available_after,
            "created_at": now,
            "explanations": row.explanations,
        },
    )
    if row.buyers:
        connection.execute(
            insert(Purchase),
            [
                {
                    "auction_id": auction_id,
                    "model_id": model_id,
                    "price": price,
                    "iteration": row.iteration,
                }
                for model_id, price in row.buyers
            ],
        )
    if row.quitters:
        connection.execute(
            insert(Quit),
            [
                {"auction_id": auction_id, "model_id": model_id, "iteration": row.iteration}
                for model_id in row.quitters
            ],
        )
    fine_tunings: list[tuple[int, bool, JSONText | None, list[dict[str, str]] | None]]
    fine_tunings = [(model_id, True, manifest, None) for model_id, manifest in row.tuned]
    fine_tunings += [(model_id, False, None, reasons) for model_id, reasons in row.refused]
    if fine_tunings:
        connection.execute(
            insert(TunedWeights),
            [
                {
                    "auction_id": auction_id,
                    "model_id": model_id,
                    "iteration": row.iteration,
                    "kept": kept,
                    "manifest": manifest,
                    "reasons": reasons,
                }
                for model_id, kept, manifest, reasons in fine_tunings
            ],
        )
    if opened is None:
        return None
    round_id = connection.execute(
        insert(FineTuneRound).returning(FineTuneRound.id),
        {
            "auction_id": auction_id,
            "round": opened.round,
            "iteration": opened.iteration,
            "status": RoundStatus.OPEN,
            "opened_at": now,
            "deadline": opened.deadline,
            "rows": opened.rows,
            "fine_tune_seed": opened.fine_tune_seed,
            "augmentation_seed": opened.augmentation_seed,
            "asked": opened.asked,
            # What publishing the round costs: its rows as JSON, once to every patron asked.
            "bytes_published": len(json.dumps(opened.rows, separators=(",", ":")))
            * len(opened.asked),
        },
    ).scalar_one()
    return StepRound(round_id, opened.round, list(opened.asked), opened.deadline, True)


_BID_WITH = (
    update(AuctionPatron)
    .where(
        AuctionPatron.auction_id == bindparam("auction"),
        AuctionPatron.position == bindparam("patron"),
    )
    .values(current_model_id=bindparam("version"))
)
"""A patron bids with an accepted version from now (one statement for a round's patrons)."""


def round_answers(connection: Connection, round_id: int) -> tuple[dict[int, int], set[int]]:
    """The round's accepted uploads (position → version id) and the positions that answered;
    ``PendingUploadsError`` if an upload still awaits its verdict."""
    answers = connection.execute(
        select(FineTuneAnswer.position, FineTuneAnswer.outcome, FineTuneAnswer.uploaded_id).where(
            FineTuneAnswer.round_id == round_id
        )
    ).all()
    if any(a.outcome == AnswerOutcome.PENDING for a in answers):
        raise PendingUploadsError(round_id)
    applied = {
        a.position: a.uploaded_id
        for a in answers
        if a.outcome == AnswerOutcome.ACCEPTED and a.uploaded_id is not None
    }
    return applied, {a.position for a in answers}


def accepted_uploads(session: Session, *, round_id: int) -> dict[int, tuple[int, dict[str, Any]]]:
    """A closed round's accepted uploads: position → (version id, manifest), for the step to
    apply."""
    connection = session.connection()
    applied, _ = round_answers(connection, round_id)
    rows = connection.execute(
        select(ModelVersion.id, ModelVersion.manifest).where(
            ModelVersion.id.in_(list(applied.values()))
        )
    )
    manifests: dict[int, dict[str, Any]] = {version: manifest for version, manifest in rows}
    return {position: (version, manifests[version]) for position, version in applied.items()}


def close_round(
    connection: Connection, *, auction_id: int, round_id: int, asked: Sequence[int], now: datetime
) -> bool:
    """Close the round at ``now`` if it is still open (False if it was not: closed at its last
    verdict, or by a cancel). ``PendingUploadsError`` (roll back) if an upload still awaits its
    verdict."""
    closed = connection.execute(
        update(FineTuneRound)
        .where(FineTuneRound.id == round_id, FineTuneRound.status == RoundStatus.OPEN)
        .values(status=RoundStatus.CLOSED, closed_at=now)
    )
    if closed.rowcount != 1:
        return False
    # Read once the round's row is written: no upload can be stored in it from here on.
    applied, heard = round_answers(connection, round_id)
    silent = [p for p in asked if p not in heard]
    settle_round(connection, auction_id=auction_id, round_id=round_id, silent=silent, now=now)
    _bid_with(connection, auction_id=auction_id, applied=applied)
    return True


def settle_round(
    connection: Connection, *, auction_id: int, round_id: int, silent: Sequence[int], now: datetime
) -> None:
    """Every asked patron that stayed ``silent`` gets a ``missing`` answer (a late upload
    keeps its own)."""
    if not silent:
        return
    bidding = {
        patron.position: patron.current_model_id or patron.model_id
        for patron in connection.execute(
            select(
                AuctionPatron.position, AuctionPatron.model_id, AuctionPatron.current_model_id
            ).where(AuctionPatron.auction_id == auction_id, AuctionPatron.position.in_(silent))
        )
    }
    connection.execute(
        insert(FineTuneAnswer),
        [
            {
                "round_id": round_id,
                "position": position,
                "outcome": AnswerOutcome.MISSING,
                "model_id": bidding[position],
                "bytes_in": 0,
                "bytes_out": 0,
                "created_at": now,
            }
            for position in silent
        ],
    )


def _bid_with(connection: Connection, *, auction_id: int, applied: dict[int, int]) -> None:
    """The patrons whose upload a closed round accepted bid with it from now (``applied``:
    position → version id)."""
    if applied:
        connection.execute(
            _BID_WITH,
            [
                {"auction": auction_id, "patron": position, "version": version}
                for position, version in applied.items()
            ],
        )
