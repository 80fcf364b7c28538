"""Auctions: creating one, cancelling one, ``GET /auctions/{id}`` (its patrons, committed
rounds, purchases, quits and, for remote auctions, its fine-tuning rounds), the auction list."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import TypeVarTuple

from sqlalchemy import Connection, Row, Select, bindparam, func, select, update
from sqlalchemy.orm import Session

from server.store.crud.lists import ListOrder, keyset
from server.store.crud.live import notify_change, notify_due
from server.store.status import AUCTION_UNFINISHED, AuctionStatus, RoundStatus
from server.store.tables import (
    Auction,
    AuctionIteration,
    AuctionPatron,
    FineTuneAnswer,
    FineTuneRound,
    ModelVersion,
    Participant,
    Purchase,
    Quit,
    utcnow,
)

# iteration, price, n_available, votes, row_votes, next_price, n_available_after
HistoryRow = Row[int, float, int, dict[str, int], dict[str, int], float, int]
# model_id, price, iteration, participant, version, version_id
PurchaseRow = Row[int, float, int, str, int, int]
# model_id, participant, version, iteration, version_id
QuitRow = Row[int, str, int, int, int]


@dataclass(frozen=True)
class AuctionHead:
    """The columns of an auction row that ``GET /auctions/{id}`` shows (no checkpoint)."""

    id: int
    status: str
    n_initial: int
    rarity: float | None
    max_iterations: int
    fine_tune: bool
    seed: int
    iteration: int
    price: float
    n_available: int
    stop_reason: str | None
    error: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    fine_tune_mode: str
    fine_tune_rounds: int
    round_deadline_s: float
    buy_fraction: str
    enroll_until: datetime | None
    n_rows: int


@dataclass(frozen=True)
class AnswerView:
    """A patron's outcome in a fine-tuning round and the version it bids with afterwards."""

    model_id: int
    """The patron (its id in the auction's ``model_ids``)."""
    outcome: str
    version: int
    version_id: int
    uploaded_id: int | None
    bytes_in: int
    bytes_out: int


@dataclass(frozen=True)
class RoundView:
    """A remote fine-tuning round as ``GET /auctions/{id}`` shows it."""

    round: int
    iteration: int
    status: str
    opened_at: datetime
    deadline: datetime
    closed_at: datetime | None
    bytes_published: int
    answers: list[AnswerView]


@dataclass(frozen=True)
class AuctionView:
    """An auction row with its ordered patrons, committed iterations, purchases and quits."""

    auction: AuctionHead
    model_ids: list[int]
    participants: list[str]
    """The participant of each patron, aligned with ``model_ids``."""
    history: Sequence[HistoryRow]
    purchases: Sequence[PurchaseRow]
    quitters: Sequence[QuitRow]
    fine_tuning: list[RoundView] = dataclasses.field(default_factory=list)
    """Remote fine-tuning rounds, oldest first (remote auctions only)."""
    current_model_ids: list[int] = dataclasses.field(default_factory=list)
    """The version each patron bids with now, aligned with ``model_ids`` (remote only)."""


def count_live(session: Session) -> int:
    """Auctions pending or running."""
    live = select(func.count()).select_from(Auction).where(Auction.status.in_(AUCTION_UNFINISHED))
    return session.scalar(live) or 0


def create_auction(
    session: Session,
    *,
    model_ids: list[int],
    n_fish: int,
    rarity: float | None,
    max_iterations: int,
    fine_tune: bool,
    seed: int,
    opening_price: float,
    fine_tune_mode: str = "server",
    fine_tune_rounds: int = 4,
    round_deadline_s: float = 10.0,
    buy_fraction: str = "all",
    enroll_until: datetime | None = None,
    n_rows: int = 64,
) -> Auction:
    """A pending auction over the ordered patron list ``model_ids``; with ``enroll_until``,
    participants may add theirs until then, when its first step falls due."""
    now = utcnow()
    auction = Auction(
        status=AuctionStatus.PENDING,
        n_initial=n_fish,
        rarity=rarity,
        max_iterations=max_iterations,
        fine_tune=fine_tune,
        fine_tune_mode=fine_tune_mode,
        fine_tune_rounds=fine_tune_rounds,
        round_deadline_s=round_deadline_s,
        buy_fraction=buy_fraction,
        n_rows=n_rows,
        seed=seed,
        iteration=0,
        price=opening_price,
        n_available=n_fish,
        created_at=now,
        updated_at=now,
        enroll_until=enroll_until,
        next_step_at=enroll_until or now,
    )
    session.add(auction)
    session.flush()
    session.add_all(
        AuctionPatron(auction_id=auction.id, position=position, model_id=model_id)
        for position, model_id in enumerate(model_ids)
    )
    notify_due(session, kind="auction")  # due now, or other replicas learn when
    return auction


@dataclass(frozen=True)
class Enrollment:
    """An auction as a participant joining it finds it, its row locked until commit."""

    status: str
    enroll_until: datetime | None
    rarity: float | None
    patrons: dict[int, tuple[int, int]]
    """Participant id → the model naming it and its position, for every patron so far."""


def lock_enrollment(session: Session, *, auction_id: int) -> Enrollment | None:
    """The auction's enrollment, its row locked until commit (joins and the start that ends
    the enrollment take turns); None if there is no such auction."""
    head = session.execute(
        select(Auction.status, Auction.enroll_until, Auction.rarity)
        .where(Auction.id == auction_id)
        .with_for_update()
    ).one_or_none()
    if head is None:
        return None
    rows = session.execute(
        select(ModelVersion.participant_id, AuctionPatron.model_id, AuctionPatron.position)
        .join(ModelVersion, ModelVersion.id == AuctionPatron.model_id)
        .where(AuctionPatron.auction_id == auction_id)
    )
    patrons = {p: (m, position) for p, m, position in rows}
    return Enrollment(head.status, head.enroll_until, head.rarity, patrons)


def add_patron(session: Session, *, auction_id: int, model_id: int, position: int) -> None:
    """A patron at the end of the auction's list (its enrollment locked: ``lock_enrollment``)."""
    session.add(AuctionPatron(auction_id=auction_id, position=position, model_id=model_id))
    session.execute(update(Auction).where(Auction.id == auction_id).values(updated_at=utcnow()))
    notify_change(session, kind="auction", row_id=auction_id)


def end_enrollment(session: Session, *, auction_id: int, n_fish: int | None) -> None:
    """Fix the patrons of an enrolling auction (its enrollment locked): no more joins, and
    with ``n_fish`` its supply (a rarity's, now that the patrons are known)."""
    values: dict[str, object] = {"enroll_until": None, "updated_at": utcnow()}
    if n_fish is not None:
        values |= {"n_initial": n_fish, "n_available": n_fish}
    session.execute(update(Auction).where(Auction.id == auction_id).values(**values))


def cancel_auction(session: Session, *, auction_id: int) -> bool:
    """Mark a pending or running auction cancelled and close its open fine-tuning round, if
    any; False when it had already ended. Its committed iterations, purchases and quits stay."""
    now = utcnow()
    # The open rounds are closed before the auction row is taken and again after: a worker
    # closing a round locks the round, then the auction (this order never deadlocks with it on
    # PostgreSQL), and a round its commit opened while we waited is closed by the second pass.
    close_open_rounds(session, auction_id, now)
    changed = session.execute(
        update(Auction)
        .where(Auction.id == auction_id, Auction.status.in_(AUCTION_UNFINISHED))
        .values(
            status=AuctionStatus.CANCELLED,
            stop_reason="cancelled",
            finished_at=now,
            updated_at=now,
            next_step_at=None,
            enroll_until=None,
        )
    )
    if not changed.rowcount:  # type: ignore[attr-defined]
        return False
    close_open_rounds(session, auction_id, now)
    notify_change(session, kind="auction", row_id=auction_id)
    return True


def close_open_rounds(session: Session, auction_id: int, now: datetime) -> None:
    """Close the auction's open fine-tuning round, if any (its auction ends)."""
    session.execute(
        update(FineTuneRound)
        .where(FineTuneRound.auction_id == auction_id, FineTuneRound.status == RoundStatus.OPEN)
        .values(status=RoundStatus.CLOSED, closed_at=now)
    )


# The statements of GET /auctions/{id}, built once and run as Core (it is polled while auctions
# run: no ORM identity map, no object loading)
_AUCTION_HEAD = select(*(getattr(Auction, f.name) for f in dataclasses.fields(AuctionHead))).where(
    Auction.id == bindparam("auction_id")
)
AUCTION_PATRONS = (
    select(AuctionPatron.model_id)
    .where(AuctionPatron.auction_id == bindparam("auction_id"))
    .order_by(AuctionPatron.position)
)

_PATRONS_NAMED = (
    select(AuctionPatron.model_id, Participant.name)
    .join(ModelVersion, ModelVersion.id == AuctionPatron.model_id)
    .join(Participant, Participant.id == ModelVersion.participant_id)
    .where(AuctionPatron.auction_id == bindparam("auction_id"))
    .order_by(AuctionPatron.position)
)


@dataclass(frozen=True)
class IterationFigures:
    """What one played iteration stores of itself (the columns of ``auction_iterations``):
    written by a step (``steps.IterationRow``), read by the event streams
    (``events.AuctionRound``) and the auction's history."""

    iteration: int
    price: float
    n_available: int
    votes: dict[str, int]
    row_votes: dict[str, int]
    next_price: float
    n_available_after: int


AUCTION_HISTORY = (
    select(*(getattr(AuctionIteration, f.name) for f in dataclasses.fields(IterationFigures)))
    .where(AuctionIteration.auction_id == bindparam("auction_id"))
    .order_by(AuctionIteration.iteration)
)


Ts = TypeVarTuple("Ts")


def bidder(query: Select[*Ts], table: type[Purchase] | type[Quit]) -> Select[*Ts]:
    """``query`` over a purchase or quit joined to the version that bid when the patron left:
    its current one (a patron is never asked again once it has bought or quit, so remote
    rounds cannot have changed it since), and that version's participant."""
    return (
        query.join(
            AuctionPatron,
            (AuctionPatron.auction_id == table.auction_id)
            & (AuctionPatron.model_id == table.model_id),
        )
        .join(
            ModelVersion,
            ModelVersion.id == func.coalesce(AuctionPatron.current_model_id, table.model_id),
        )
        .join(Participant, Participant.id == ModelVersion.participant_id)
    )


_AUCTION_PURCHASES = (
    bidder(
        select(
            Purchase.model_id,
            Purchase.price,
            Purchase.iteration,
            Participant.name.label("participant"),
            ModelVersion.version,
            ModelVersion.id.label("version_id"),
        ),
        Purchase,
    )
    .where(Purchase.auction_id == bindparam("auction_id"))
    .order_by(Purchase.id)
)
_AUCTION_QUITTERS = (
    bidder(
        select(
            Quit.model_id,
            Participant.name.label("participant"),
            ModelVersion.version,
            Quit.iteration,
            ModelVersion.id.label("version_id"),
        ),
        Quit,
    )
    .where(Quit.auction_id == bindparam("auction_id"))
    .order_by(Quit.id)
)


def snapshot(session: Session) -> Connection:
    """The session's connection, its statements reading one snapshot. PostgreSQL's default
    isolation (READ COMMITTED) gives each statement its own: an auction read while a step
    committed had shown iteration 0 with a history row, or buyers its history did not hold yet
    (1-8 % of reads, under a load of readers). SQLite's transaction reads one snapshot anyway.
    A session already in a transaction keeps it."""
    if session.in_transaction() or session.get_bind().dialect.name != "postgresql":
        return session.connection()
    return session.connection(execution_options={"isolation_level": "REPEATABLE READ"})


def get_auction(session: Session, *, auction_id: int) -> AuctionView | None:
    """An auction with its patrons, rounds, purchases and quits, read in one transaction from
    one snapshot (``snapshot``)."""
    key = {"auction_id": auction_id}
    connection = snapshot(session)
    head = connection.execute(_AUCTION_HEAD, key).one_or_none()
    if head is None:
        return None
    auction = AuctionHead(*head)
    patrons = connection.execute(_PATRONS_NAMED, key).all()
    model_ids = [model_id for model_id, _ in patrons]
    return AuctionView(
        auction,
        model_ids,
        [name for _, name in patrons],
        connection.execute(AUCTION_HISTORY, key).all(),
        connection.execute(_AUCTION_PURCHASES, key).all(),
        connection.execute(_AUCTION_QUITTERS, key).all(),
        *(
            (_fine_tuning(session, auction_id, model_ids), _current_versions(session, auction_id))
            if auction.fine_tune_mode == "remote"
            else ([], [])
        ),
    )


@dataclass(frozen=True)
class AuctionSummary:
    """An auction as a list shows it."""

    id: int
    status: str
    n_initial: int
    n_available: int
    n_patrons: int
    iteration: int
    price: float
    revenue: float
    stop_reason: str | None
    rarity: float | None
    fine_tune: bool
    created_at: datetime
    finished_at: datetime | None


_N_PATRONS = (
    select(func.count())
    .where(AuctionPatron.auction_id == Auction.id)
    .correlate(Auction)
    .scalar_subquery()
)
_REVENUE = (
    select(func.coalesce(func.sum(Purchase.price), 0.0))
    .where(Purchase.auction_id == Auction.id)
    .correlate(Auction)
    .scalar_subquery()
)
_AUCTION_SUMMARY = select(
    Auction.id,
    Auction.status,
    Auction.n_initial,
    Auction.n_available,
    _N_PATRONS,
    Auction.iteration,
    Auction.price,
    _REVENUE,
    Auction.stop_reason,
    Auction.rarity,
    Auction.fine_tune,
    Auction.created_at,
    Auction.finished_at,
).order_by(Auction.id.desc())


def list_auctions(
    session: Session,
    *,
    before: int | None,
    limit: int,
    status: str | None = None,
    order: ListOrder = "newest",
) -> list[AuctionSummary]:
    """Up to ``limit`` auctions after the cursor ``before`` in ``order``, of ``status`` if
    given (one query)."""
    query = keyset(_AUCTION_SUMMARY, Auction.id, cursor=before, order=order).limit(limit)
    if status is not None:
        query = query.where(Auction.status == status)
    return [AuctionSummary(*row) for row in session.connection().execute(query)]


def round_status_after(session: Session, *, auction_id: int, iteration: int) -> str | None:
    """The status of the auction's remote fine-tuning round after ``iteration`` (None: none)."""
    status: str | None = session.execute(
        select(FineTuneRound.status).where(
            FineTuneRound.auction_id == auction_id, FineTuneRound.iteration == iteration
        )
    ).scalar()
    return status


def fine_tune_rounds(session: Session, *, auction_id: int) -> list[RoundView]:
    """An auction's remote fine-tuning rounds, oldest first, with every patron's outcome."""
    model_ids = list(session.connection().scalars(AUCTION_PATRONS, {"auction_id": auction_id}))
    return _fine_tuning(session, auction_id, model_ids)


# The remote fine-tuning rounds of an auction, for GET /auctions/{id} and its event stream
_ROUNDS_OF_AUCTION = (
    select(FineTuneRound)
    .where(FineTuneRound.auction_id == bindparam("auction_id"))
    .order_by(FineTuneRound.round)
)
_ANSWERS_OF_AUCTION = (
    select(
        FineTuneAnswer.round_id,
        FineTuneAnswer.position,
        FineTuneAnswer.outcome,
        FineTuneAnswer.model_id,
        ModelVersion.version,
        FineTuneAnswer.uploaded_id,
        FineTuneAnswer.bytes_in,
        FineTuneAnswer.bytes_out,
    )
    .join(FineTuneRound, FineTuneRound.id == FineTuneAnswer.round_id)
    .join(ModelVersion, ModelVersion.id == FineTuneAnswer.model_id)
    .where(FineTuneRound.auction_id == bindparam("auction_id"))
    .order_by(FineTuneAnswer.round_id, FineTuneAnswer.position)
)


def _current_versions(session: Session, auction_id: int) -> list[int]:
    """The version each patron bids with now, in patron order (one query)."""
    return list(
        session.connection().scalars(
            select(func.coalesce(AuctionPatron.current_model_id, AuctionPatron.model_id))
            .where(AuctionPatron.auction_id == auction_id)
            .order_by(AuctionPatron.position)
        )
    )


def _fine_tuning(session: Session, auction_id: int, model_ids: list[int]) -> list[RoundView]:
    """The auction's fine-tuning rounds with every patron's outcome (two queries). The rounds
    are read first: a round closes in the transaction that writes its last answers, so on a
    database whose every statement sees the newest commits (PostgreSQL's read committed) a round
    read closed never shows without them."""
    key = {"auction_id": auction_id}
    rounds = list(session.scalars(_ROUNDS_OF_AUCTION, key))
    answers: dict[int, list[AnswerView]] = {}
    for row in session.connection().execute(_ANSWERS_OF_AUCTION, key):
        answers.setdefault(row.round_id, []).append(
            AnswerView(
                model_ids[row.position],
                row.outcome,
                row.version,
                row.model_id,
                row.uploaded_id,
                row.bytes_in,
                row.bytes_out,
            )
        )
    return [
        RoundView(
            r.round,
            r.iteration,
            r.status,
            r.opened_at,
            r.deadline,
            r.closed_at,
            r.bytes_published,
            answers.get(r.id, []),
        )
        for r in rounds
    ]
