"""Database reads and writes used by the routes (keyword-only, no commits: the route commits)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import Row, bindparam, func, insert, select, update
from sqlalchemy.orm import Session

from server.models import (
    Auction,
    AuctionIteration,
    AuctionPatron,
    FineTuneAnswer,
    FineTuneRound,
    Job,
    ModelVersion,
    Participant,
    Purchase,
    Quit,
    utcnow,
)
from server.status import AUCTION_UNFINISHED, JOB_UNFINISHED, AuctionStatus, JobStatus

PARTICIPANT_TOKEN_PREFIX = "srdp"
# iteration, price, n_available, votes, row_votes, next_price, n_available_after
HistoryRow = Row[int, float, int, dict[str, int], dict[str, int], float, int]
PurchaseRow = Row[int, float, int]  # model_id, price, iteration


@dataclass(frozen=True)
class ParticipantRow:
    """The columns of a participant that a submission needs."""

    id: int
    name: str
    token_hash: str


@dataclass(frozen=True)
class StoredModel:
    """A model version as ``GET /models/{id}`` shows it."""

    id: int
    participant: str
    version: int
    manifest: dict[str, Any]
    accepted: bool
    reasons: list[dict[str, str]]
    created_at: datetime
    parent_id: int | None = None
    auction_id: int | None = None
    round: int | None = None
    auctions: tuple[int, ...] = ()
    """Auctions it entered as a patron, newest first (``get_model_view`` only)."""


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
    """An auction row with its ordered patrons, committed rounds, purchases and quits."""

    auction: AuctionHead
    model_ids: list[int]
    history: Sequence[HistoryRow]
    purchases: Sequence[PurchaseRow]
    quitters: list[int]
    fine_tuning: list[RoundView] = dataclasses.field(default_factory=list)
    """Remote fine-tuning rounds, oldest first (remote auctions only)."""
    current_model_ids: list[int] = dataclasses.field(default_factory=list)
    """The version each patron bids with now, aligned with ``model_ids`` (remote only)."""


# The statements of POST /submit, built once and run on the session's connection (Core, not the
# ORM's bulk-insert path: the hot path builds and tracks no objects)
_PARTICIPANTS_BY_NAMES = (
    select(Participant.id, Participant.name, Participant.token_hash)
    .where(Participant.name.in_(bindparam("names", expanding=True)))
    .order_by(Participant.id)
    .with_for_update()
)
_LATEST_VERSIONS = (
    select(ModelVersion.participant_id, func.max(ModelVersion.version))
    .where(ModelVersion.participant_id.in_(bindparam("ids", expanding=True)))
    .group_by(ModelVersion.participant_id)
)
_INSERT_PARTICIPANTS = insert(Participant).returning(Participant.id, sort_by_parameter_order=True)
_INSERT_MODEL_VERSIONS = insert(ModelVersion).returning(
    ModelVersion.id, sort_by_parameter_order=True
)


def participants_by_names(session: Session, *, names: Sequence[str]) -> dict[str, ParticipantRow]:
    """The participants among ``names``, their rows locked until commit (one query)."""
    rows = session.connection().execute(_PARTICIPANTS_BY_NAMES, {"names": list(names)})
    return {row.name: ParticipantRow(*row) for row in rows}


def latest_versions(session: Session, *, participant_ids: Sequence[int]) -> dict[int, int]:
    """The newest version number of each of these participants (one query)."""
    if not participant_ids:
        return {}
    rows = session.connection().execute(_LATEST_VERSIONS, {"ids": list(participant_ids)})
    return {participant_id: version for participant_id, version in rows}


def insert_participants(session: Session, *, rows: Sequence[dict[str, Any]]) -> list[int]:
    """Insert participants (``name``, ``token_hash``, ``created_at``); their ids, in order."""
    if not rows:
        return []
    return list(session.connection().execute(_INSERT_PARTICIPANTS, list(rows)).scalars())


def insert_model_versions(session: Session, *, rows: Sequence[dict[str, Any]]) -> list[int]:
    """Insert model versions (all columns but ``id``); their ids, in order."""
    if not rows:
        return []
    return list(session.connection().execute(_INSERT_MODEL_VERSIONS, list(rows)).scalars())


_MODEL_BY_ID = (
    select(
        ModelVersion.id,
        Participant.name,
        ModelVersion.version,
        ModelVersion.manifest,
        ModelVersion.accepted,
        ModelVersion.reasons,
        ModelVersion.created_at,
        ModelVersion.parent_id,
        ModelVersion.auction_id,
        ModelVersion.round,
    )
    .join(Participant, Participant.id == ModelVersion.participant_id)
    .where(ModelVersion.id == bindparam("model_id"))
)


def get_model(session: Session, *, model_id: int) -> StoredModel | None:
    """A model version with its participant's name (one query)."""
    row = session.connection().execute(_MODEL_BY_ID, {"model_id": model_id}).one_or_none()
    return None if row is None else StoredModel(*row)


def get_model_view(session: Session, *, model_id: int, auctions: int) -> StoredModel | None:
    """``get_model`` with the ``auctions`` newest auctions it entered (two queries)."""
    row = get_model(session, model_id=model_id)
    if row is None:
        return None
    entered = patron_auctions(session, model_id=model_id, limit=auctions)
    return dataclasses.replace(row, auctions=tuple(entered))


def get_models(session: Session, *, model_ids: list[int]) -> dict[int, ModelVersion]:
    """Model versions by id (missing ids are absent from the result)."""
    rows = session.scalars(select(ModelVersion).where(ModelVersion.id.in_(model_ids))).all()
    return {row.id: row for row in rows}


def latest_accepted_models(session: Session) -> list[ModelVersion]:
    """The newest accepted version of every participant, in participant order."""
    newest = (
        select(ModelVersion.participant_id, func.max(ModelVersion.version).label("version"))
        .where(ModelVersion.accepted.is_(True))
        .group_by(ModelVersion.participant_id)
        .subquery()
    )
    query = (
        select(ModelVersion)
        .join(
            newest,
            (ModelVersion.participant_id == newest.c.participant_id)
            & (ModelVersion.version == newest.c.version),
        )
        .order_by(ModelVersion.participant_id)
    )
    return list(session.scalars(query).all())


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
) -> Auction:
    """A pending auction over the ordered patron list ``model_ids``."""
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
        seed=seed,
        iteration=0,
        price=opening_price,
        n_available=n_fish,
        created_at=now,
        updated_at=now,
    )
    session.add(auction)
    session.flush()
    session.add_all(
        AuctionPatron(auction_id=auction.id, position=position, model_id=model_id)
        for position, model_id in enumerate(model_ids)
    )
    return auction


# The statements of GET /auctions/{id}, built once and run as Core (it is polled while auctions
# run: no ORM identity map, no object loading)
_AUCTION_HEAD = select(*(getattr(Auction, f.name) for f in dataclasses.fields(AuctionHead))).where(
    Auction.id == bindparam("auction_id")
)
_AUCTION_PATRONS = (
    select(AuctionPatron.model_id)
    .where(AuctionPatron.auction_id == bindparam("auction_id"))
    .order_by(AuctionPatron.position)
)
_AUCTION_HISTORY = (
    select(
        AuctionIteration.iteration,
        AuctionIteration.price,
        AuctionIteration.n_available,
        AuctionIteration.votes,
        AuctionIteration.row_votes,
        AuctionIteration.next_price,
        AuctionIteration.n_available_after,
    )
    .where(AuctionIteration.auction_id == bindparam("auction_id"))
    .order_by(AuctionIteration.iteration)
)
_AUCTION_PURCHASES = (
    select(Purchase.model_id, Purchase.price, Purchase.iteration)
    .where(Purchase.auction_id == bindparam("auction_id"))
    .order_by(Purchase.id)
)
_AUCTION_QUITTERS = (
    select(Quit.model_id).where(Quit.auction_id == bindparam("auction_id")).order_by(Quit.id)
)


def get_auction(session: Session, *, auction_id: int) -> AuctionView | None:
    """An auction with its patrons, rounds, purchases and quits, read in one transaction."""
    key = {"auction_id": auction_id}
    connection = session.connection()
    head = connection.execute(_AUCTION_HEAD, key).one_or_none()
    if head is None:
        return None
    auction = AuctionHead(*head)
    model_ids = list(connection.scalars(_AUCTION_PATRONS, key))
    return AuctionView(
        auction,
        model_ids,
        connection.execute(_AUCTION_HISTORY, key).all(),
        connection.execute(_AUCTION_PURCHASES, key).all(),
        list(connection.scalars(_AUCTION_QUITTERS, key)),
        *(
            (_fine_tuning(session, auction_id, model_ids), _current_versions(session, auction_id))
            if auction.fine_tune_mode == "remote"
            else ([], [])
        ),
    )


def create_job(session: Session, *, kind: str, params: dict[str, Any]) -> Job:
    """A queued job."""
    now = utcnow()
    job = Job(
        kind=kind,
        params=params,
        status=JobStatus.QUEUED,
        progress=0.0,
        message="queued",
        artifacts=[],
        attempt=0,
        created_at=now,
        updated_at=now,
    )
    session.add(job)
    session.flush()
    return job


def get_job(session: Session, *, job_id: int) -> Job | None:
    """A job by id."""
    return session.get(Job, job_id)


def fail_unfinished(
    session: Session, *, table: type[Auction] | type[Job], row_id: int, error: str
) -> None:
    """Mark an auction or job failed with ``error``, unless it has already ended."""
    unfinished, failed = (
        (AUCTION_UNFINISHED, AuctionStatus.FAILED)
        if table is Auction
        else (JOB_UNFINISHED, JobStatus.FAILED)
    )
    now = utcnow()
    values: dict[str, Any] = {"status": failed, "error": error, "finished_at": now}
    if table is Job:
        values["message"] = "failed"
    session.execute(
        update(table)
        .where(table.id == row_id, table.status.in_(unfinished))
        .values(updated_at=now, **values)
    )


def cancel_job(session: Session, *, job_id: int) -> bool:
    """Mark a queued or running job cancelled; False when it had already ended."""
    now = utcnow()
    changed = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.status.in_(JOB_UNFINISHED))
        .values(status=JobStatus.CANCELLED, message="cancelled", finished_at=now, updated_at=now)
    )
    return bool(changed.rowcount)  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------------------------
# Lists, newest first. Pages are keyset pages on the id: ``before`` is the last id of the
# previous page (the routes wrap it in an opaque cursor), so a page costs one index range scan
# however deep it is, and rows added meanwhile never shift a page.


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


def list_auctions(session: Session, *, before: int | None, limit: int) -> list[AuctionSummary]:
    """Up to ``limit`` auctions with ids below ``before``, newest first (one query)."""
    query = _AUCTION_SUMMARY.limit(limit)
    if before is not None:
        query = query.where(Auction.id < before)
    return [AuctionSummary(*row) for row in session.connection().execute(query)]


@dataclass(frozen=True)
class ModelSummary:
    """A model version as a list shows it: who, which version, the verdict and its reasons."""

    id: int
    participant: str
    version: int
    accepted: bool
    description: str | None
    reasons: list[dict[str, str]]
    created_at: datetime


_MODEL_SUMMARY = (
    select(
        ModelVersion.id,
        Participant.name,
        ModelVersion.version,
        ModelVersion.accepted,
        ModelVersion.manifest["description"].as_string(),
        ModelVersion.reasons,
        ModelVersion.created_at,
    )
    .join(Participant, Participant.id == ModelVersion.participant_id)
    .order_by(ModelVersion.id.desc())
)


def list_models(
    session: Session,
    *,
    before: int | None,
    limit: int,
    participant: str | None = None,
    accepted: bool | None = None,
) -> list[ModelSummary]:
    """Up to ``limit`` model versions with ids below ``before``, newest first, optionally of
    one participant and/or with one verdict (one query)."""
    query = _MODEL_SUMMARY.limit(limit)
    if before is not None:
        query = query.where(ModelVersion.id < before)
    if participant is not None:
        query = query.where(Participant.name == participant)
    if accepted is not None:
        query = query.where(ModelVersion.accepted.is_(accepted))
    return [ModelSummary(*row) for row in session.connection().execute(query)]


@dataclass(frozen=True)
class JobSummary:
    """A job as a list shows it (no result, no error text: those are on the job itself)."""

    id: int
    kind: str
    status: str
    progress: float
    message: str
    params: dict[str, Any]
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


_JOB_SUMMARY = select(*(getattr(Job, f.name) for f in dataclasses.fields(JobSummary))).order_by(
    Job.id.desc()
)


def list_jobs(session: Session, *, before: int | None, limit: int) -> list[JobSummary]:
    """Up to ``limit`` jobs with ids below ``before``, newest first (one query)."""
    query = _JOB_SUMMARY.limit(limit)
    if before is not None:
        query = query.where(Job.id < before)
    return [JobSummary(*row) for row in session.connection().execute(query)]


@dataclass(frozen=True)
class ParticipantView:
    """A participant: when it registered, how many versions it has, the newest of them."""

    name: str
    created_at: datetime
    n_versions: int
    versions: list[ModelSummary]


def get_participant(session: Session, *, name: str, limit: int) -> ParticipantView | None:
    """A participant by name with its ``limit`` newest versions."""
    row = (
        session.connection()
        .execute(select(Participant.id, Participant.created_at).where(Participant.name == name))
        .one_or_none()
    )
    if row is None:
        return None
    n_versions = session.connection().scalar(
        select(func.count()).where(ModelVersion.participant_id == row.id)
    )
    versions = list_models(session, before=None, limit=limit, participant=name)
    return ParticipantView(name, row.created_at, int(n_versions or 0), versions)


# ---------------------------------------------------------------------------------------------
# What the event streams poll: a few columns of the watched row, then only the rounds that are
# new since the last poll.


@dataclass(frozen=True)
class AuctionState:
    """Where an auction stands, as its event stream polls it."""

    status: str
    iteration: int
    price: float
    n_available: int
    n_initial: int
    stop_reason: str | None
    error: str | None
    finished_at: datetime | None
    fine_tune_mode: str
    updated_at: datetime
    """Moves with every write to the auction, a fine-tuning round closing included."""


@dataclass(frozen=True)
class PatronRef:
    """A patron by its model id, with the participant and version behind it."""

    model_id: int
    participant: str
    version: int


@dataclass(frozen=True)
class RoundPurchase:
    patron: PatronRef
    price: float


@dataclass(frozen=True)
class AuctionRound:
    """One committed round with the purchases and quits it made."""

    iteration: int
    price: float
    n_available: int
    votes: dict[str, int]
    row_votes: dict[str, int]
    next_price: float
    n_available_after: int
    purchases: tuple[RoundPurchase, ...]
    quits: tuple[PatronRef, ...]


_AUCTION_STATE = select(
    *(getattr(Auction, f.name) for f in dataclasses.fields(AuctionState))
).where(Auction.id == bindparam("auction_id"))
_ROUNDS = _AUCTION_HISTORY.where(AuctionIteration.iteration >= bindparam("first")).where(
    AuctionIteration.iteration < bindparam("stop")
)
_ROUND_PURCHASES = (
    select(
        Purchase.iteration,
        Purchase.model_id,
        Participant.name,
        ModelVersion.version,
        Purchase.price,
    )
    .join(ModelVersion, ModelVersion.id == Purchase.model_id)
    .join(Participant, Participant.id == ModelVersion.participant_id)
    .where(Purchase.auction_id == bindparam("auction_id"))
    .where(Purchase.iteration >= bindparam("first"))
    .where(Purchase.iteration < bindparam("stop"))
    .order_by(Purchase.id)
)
_ROUND_QUITS = (
    select(Quit.iteration, Quit.model_id, Participant.name, ModelVersion.version)
    .join(ModelVersion, ModelVersion.id == Quit.model_id)
    .join(Participant, Participant.id == ModelVersion.participant_id)
    .where(Quit.auction_id == bindparam("auction_id"))
    .where(Quit.iteration >= bindparam("first"))
    .where(Quit.iteration < bindparam("stop"))
    .order_by(Quit.id)
)


def auction_state(session: Session, *, auction_id: int) -> AuctionState | None:
    """The few columns of an auction its event stream polls (one query)."""
    row = session.connection().execute(_AUCTION_STATE, {"auction_id": auction_id}).one_or_none()
    return None if row is None else AuctionState(*row)


def auction_rounds(
    session: Session, *, auction_id: int, first: int, stop: int
) -> list[AuctionRound]:
    """Rounds ``first`` .. ``stop - 1`` of an auction with their purchases and quits, each
    patron named (three queries). Pass ``stop`` = the auction's committed ``iteration`` read
    before: a round is committed with its purchases and quits, so all of them are seen."""
    key = {"auction_id": auction_id, "first": first, "stop": stop}
    connection = session.connection()
    purchases: dict[int, list[RoundPurchase]] = {}
    for iteration, model_id, name, version, price in connection.execute(_ROUND_PURCHASES, key):
        purchases.setdefault(iteration, []).append(
            RoundPurchase(PatronRef(model_id, name, version), price)
        )
    quits: dict[int, list[PatronRef]] = {}
    for iteration, model_id, name, version in connection.execute(_ROUND_QUITS, key):
        quits.setdefault(iteration, []).append(PatronRef(model_id, name, version))
    return [
        AuctionRound(
            *row,
            purchases=tuple(purchases.get(row.iteration, ())),
            quits=tuple(quits.get(row.iteration, ())),
        )
        for row in connection.execute(_ROUNDS, key)
    ]


def fine_tune_rounds(session: Session, *, auction_id: int) -> list[RoundView]:
    """An auction's remote fine-tuning rounds, oldest first, with every patron's outcome."""
    model_ids = list(session.connection().scalars(_AUCTION_PATRONS, {"auction_id": auction_id}))
    return _fine_tuning(session, auction_id, model_ids)


@dataclass(frozen=True)
class JobState:
    """Where a job stands, as its event stream polls it (the result is read once, at the end)."""

    status: str
    progress: float
    message: str
    attempt: int
    updated_at: datetime


_JOB_STATE = select(*(getattr(Job, f.name) for f in dataclasses.fields(JobState))).where(
    Job.id == bindparam("job_id")
)


def job_state(session: Session, *, job_id: int) -> JobState | None:
    """The few columns of a job its event stream polls (one query)."""
    row = session.connection().execute(_JOB_STATE, {"job_id": job_id}).one_or_none()
    return None if row is None else JobState(*row)


# ---------------------------------------------------------------------------------------------
# Remote fine-tuning rounds: what the round watcher polls, what an upload checks, the rounds of
# GET /auctions/{id}. (The worker opens and closes rounds itself, see server.auctions.)

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
    """The auction's fine-tuning rounds with every patron's outcome (two queries)."""
    key = {"auction_id": auction_id}
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
        for r in session.scalars(_ROUNDS_OF_AUCTION, key)
    ]


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
    model_ids = list(connection.scalars(_AUCTION_PATRONS, {"auction_id": row.auction_id}))
    return RoundBody(
        row.rows,
        row.fine_tune_seed,
        row.augmentation_seed,
        [model_ids[position] for position in row.asked],
    )


def add_published_bytes(session: Session, *, counts: dict[int, int]) -> None:
    """Add bytes of published round answers to their rounds' counters (``round id → bytes``)."""
    for round_id, n_bytes in counts.items():
        session.execute(
            update(FineTuneRound)
            .where(FineTuneRound.id == round_id)
            .values(bytes_published=FineTuneRound.bytes_published + n_bytes)
        )


@dataclass(frozen=True)
class UploadTarget:
    """What ``PUT /auctions/{id}/rounds/{round}/models/{model_id}`` checks before screening."""

    auction_status: str
    fine_tune_mode: str
    position: int | None
    """The model's position among the auction's patrons (None: not a patron)."""
    participant_id: int
    participant: str
    token_hash: str
    current_id: int
    """The version the patron bids with now."""
    current_version: int
    current_manifest: dict[str, Any]
    newest_round: int | None
    newest_status: str | None
    round_id: int | None
    """The path's round, if the auction has it."""
    round_status: str | None
    deadline: datetime | None
    asked: list[int]
    answer_outcome: str | None
    """This patron's answer in the path's round so far, if any."""
    answer_sha256: str | None
    answer: dict[str, Any] | None


class UploadLookupError(LookupError):
    """The auction or the model of an upload's path does not exist (``field`` names which)."""

    def __init__(self, field: str) -> None:
        super().__init__(field)
        self.field = field


UploadKey = tuple[int, int, int]
"""(auction id, model id, round) of an upload's path."""


def upload_targets(
    session: Session, *, keys: Sequence[UploadKey]
) -> list[UploadTarget | UploadLookupError]:
    """What each upload of a batch is checked against, read in one transaction with six
    queries whatever the batch's size (the UploadLookupError of a path that names no auction
    or model)."""
    connection = session.connection()
    auction_ids = sorted({a for a, _, _ in keys})
    model_ids = sorted({m for _, m, _ in keys})
    auctions = {
        row.id: row
        for row in connection.execute(
            select(Auction.id, Auction.status, Auction.fine_tune_mode).where(
                Auction.id.in_(auction_ids)
            )
        )
    }
    owners = {
        row.id: row
        for row in connection.execute(
            select(
                ModelVersion.id,
                Participant.id.label("participant_id"),
                Participant.name,
                Participant.token_hash,
            )
            .join(Participant, Participant.id == ModelVersion.participant_id)
            .where(ModelVersion.id.in_(model_ids))
        )
    }
    patrons = {
        (row.auction_id, row.model_id): row
        for row in connection.execute(
            select(
                AuctionPatron.auction_id,
                AuctionPatron.model_id,
                AuctionPatron.position,
                AuctionPatron.current_model_id,
            ).where(
                AuctionPatron.auction_id.in_(auction_ids), AuctionPatron.model_id.in_(model_ids)
            )
        )
    }

    def current_of(auction_id: int, model_id: int) -> int:
        patron = patrons.get((auction_id, model_id))
        return (
            model_id
            if patron is None or patron.current_model_id is None
            else (patron.current_model_id)
        )

    versions = {
        row.id: row
        for row in connection.execute(
            select(ModelVersion.id, ModelVersion.version, ModelVersion.manifest).where(
                ModelVersion.id.in_(sorted({current_of(a, m) for a, m, _ in keys}))
            )
        )
    }
    rounds: dict[int, dict[int, Any]] = {}
    for row in connection.execute(
        select(
            FineTuneRound.id,
            FineTuneRound.auction_id,
            FineTuneRound.round,
            FineTuneRound.status,
            FineTuneRound.deadline,
            FineTuneRound.asked,
        ).where(FineTuneRound.auction_id.in_(auction_ids))
    ):
        rounds.setdefault(row.auction_id, {})[row.round] = row
    asked_ids = sorted({r.id for a, _, n in keys if (r := rounds.get(a, {}).get(n))})
    positions = sorted({p.position for p in patrons.values()})
    answers = {
        (row.round_id, row.position): row
        for row in connection.execute(
            select(
                FineTuneAnswer.round_id,
                FineTuneAnswer.position,
                FineTuneAnswer.outcome,
                FineTuneAnswer.body_sha256,
                FineTuneAnswer.answer,
            ).where(FineTuneAnswer.round_id.in_(asked_ids), FineTuneAnswer.position.in_(positions))
        )
    }
    out: list[UploadTarget | UploadLookupError] = []
    for auction_id, model_id, number in keys:
        auction, owner = auctions.get(auction_id), owners.get(model_id)
        if auction is None or owner is None:
            out.append(UploadLookupError("auction_id" if auction is None else "model_id"))
            continue
        patron = patrons.get((auction_id, model_id))
        current = versions[current_of(auction_id, model_id)]
        mine = rounds.get(auction_id, {})
        newest = mine[max(mine)] if mine else None
        asked = mine.get(number)
        answer = None
        if asked is not None and patron is not None:
            answer = answers.get((asked.id, patron.position))
        out.append(
            UploadTarget(
                auction_status=auction.status,
                fine_tune_mode=auction.fine_tune_mode,
                position=None if patron is None else patron.position,
                participant_id=owner.participant_id,
                participant=owner.name,
                token_hash=owner.token_hash,
                current_id=current.id,
                current_version=current.version,
                current_manifest=current.manifest,
                newest_round=None if newest is None else newest.round,
                newest_status=None if newest is None else newest.status,
                round_id=None if asked is None else asked.id,
                round_status=None if asked is None else asked.status,
                deadline=None if asked is None else asked.deadline,
                asked=[] if asked is None else list(asked.asked),
                answer_outcome=None if answer is None else answer.outcome,
                answer_sha256=None if answer is None else answer.body_sha256,
                answer=None if answer is None else answer.answer,
            )
        )
    return out


def patron_auctions(session: Session, *, model_id: int, limit: int) -> list[int]:
    """Ids of the auctions this model entered as a patron, newest first (at most ``limit``)."""
    return list(
        session.connection().scalars(
            select(AuctionPatron.auction_id)
            .where(AuctionPatron.model_id == model_id)
            .order_by(AuctionPatron.auction_id.desc())
            .limit(limit)
        )
    )
