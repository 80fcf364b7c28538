"""Participants and model versions: the statements of ``POST /submit``, a model and its
auctions, the newest accepted versions, the model list and a participant."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import (
    ColumnElement,
    ScalarSelect,
    bindparam,
    case,
    func,
    insert,
    select,
    update,
)
from sqlalchemy.orm import Session

from server.store.tables import (
    Auction,
    AuctionPatron,
    ModelVersion,
    Participant,
    Purchase,
    Quit,
    Review,
    participant_key,
)

PARTICIPANT_TOKEN_PREFIX = "srdp"


@dataclass(frozen=True)
class ParticipantRow:
    """The columns of a participant that a submission needs."""

    id: int
    name: str
    name_key: str
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
    status: str = "accepted"
    """accepted | refused | held (``ModelStatus``)."""
    evidence: list[dict[str, Any]] | None = None
    auctions: tuple[int, ...] = ()
    """Auctions it entered as a patron, newest first (``get_model_view`` only)."""
    reviews: tuple[ReviewEntry, ...] = ()
    """Its audit log, oldest first (``get_model_view`` only)."""
    patron_id: int | None = None
    """For an upload of a remote round, the version its participant entered that auction with,
    for which it bids (``get_model_view`` only)."""


@dataclass(frozen=True)
class ReviewEntry:
    """An entry of a model's audit log: a decision (admit, refuse) or an appeal."""

    decision: str
    inspector: str
    note: str
    at: datetime


def is_participant_token(session: Session, token_hash: str) -> bool:
    """Whether ``token_hash`` is a participant's token's (one indexed read)."""
    found = session.execute(
        select(Participant.id).where(Participant.token_hash == token_hash).limit(1)
    )
    return found.first() is not None


def _naming(name: Any, key: Any) -> tuple[ColumnElement[bool], ColumnElement[int]]:
    """Which participants a name (and its ``participant_key``) may name, and their order: the
    one registered under it exactly first, then the one whose name reads the same (names
    registered before their keys were made unique, which now read alike, each keep their
    own)."""
    exact = Participant.name == name
    return exact | (Participant.name_key == key), case((exact, 0), else_=1)


# The statements of POST /submit, built once and run on the session's connection (Core, not the
# ORM's bulk-insert path: the hot path builds and tracks no objects)
_NAMED_WHERE, _NAMED_FIRST = _naming(bindparam("name"), bindparam("key"))
_PARTICIPANT_BY_NAME = (
    select(Participant.id, Participant.name, Participant.name_key, Participant.token_hash)
    .where(_NAMED_WHERE)
    .order_by(_NAMED_FIRST)
    .with_for_update()
)
_LATEST_VERSION = select(func.max(ModelVersion.version)).where(
    ModelVersion.participant_id == bindparam("id")
)
_INSERT_PARTICIPANT = insert(Participant).returning(Participant.id)
_INSERT_MODEL_VERSION = insert(ModelVersion).returning(ModelVersion.id)


def participant_by_name(session: Session, *, name: str) -> ParticipantRow | None:
    """The participant named ``name``, or else whose name is the same but for case, Unicode
    form or look-alike characters (``participant_key``: unique, so at most one; a name stored
    before its key was unique keeps its participant), its row locked until commit."""
    row = (
        session.connection()
        .execute(_PARTICIPANT_BY_NAME, {"name": name, "key": participant_key(name)})
        .first()
    )
    return None if row is None else ParticipantRow(*row)


def set_token_hash(session: Session, *, participant_id: int, token_hash: str) -> None:
    """Give the participant a new token (its hash): the old one is refused from now on."""
    session.execute(
        update(Participant).where(Participant.id == participant_id).values(token_hash=token_hash)
    )


def latest_version(session: Session, *, participant_id: int) -> int:
    """The participant's newest version number (0: none yet)."""
    return int(session.connection().execute(_LATEST_VERSION, {"id": participant_id}).scalar() or 0)


NEWEST_EVIDENCE_READ = 200
"""Versions read, newest first, to find the newest verdict made by a market-impact test."""


def newest_populations(session: Session) -> str | None:
    """The populations (``screener.secret.marker_of``) of the newest stored verdict whose
    market-impact test named them, among the newest ``NEWEST_EVIDENCE_READ`` versions; None if
    none did."""
    rows = session.connection().execute(
        select(ModelVersion.evidence)
        .where(ModelVersion.evidence.is_not(None))
        .order_by(ModelVersion.id.desc())
        .limit(NEWEST_EVIDENCE_READ)
    )
    for (evidence,) in rows:
        for item in evidence or []:
            marker = (item.get("detail") or {}).get("populations")
            if item.get("test") == "market-impact" and isinstance(marker, str):
                return marker
    return None


def insert_participant(session: Session, *, name: str, token_hash: str, now: datetime) -> int:
    """Insert a participant; its id."""
    values = {"name": name, "token_hash": token_hash, "created_at": now}
    return int(session.connection().execute(_INSERT_PARTICIPANT, values).scalar_one())


def insert_model_version(session: Session, *, values: dict[str, Any]) -> int:
    """Insert a model version (every column but ``id``); its id."""
    return int(session.connection().execute(_INSERT_MODEL_VERSION, values).scalar_one())


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
        ModelVersion.status,
        ModelVersion.evidence,
    )
    .join(Participant, Participant.id == ModelVersion.participant_id)
    .where(ModelVersion.id == bindparam("model_id"))
)


def get_model(session: Session, *, model_id: int) -> StoredModel | None:
    """A model version with its participant's name (one query)."""
    row = session.connection().execute(_MODEL_BY_ID, {"model_id": model_id}).one_or_none()
    return None if row is None else StoredModel(*row)


def get_model_view(session: Session, *, model_id: int, auctions: int) -> StoredModel | None:
    """``get_model`` with the ``auctions`` newest auctions it entered, its audit log and, for
    an upload, its patron (three or four queries)."""
    row = get_model(session, model_id=model_id)
    if row is None:
        return None
    entered = patron_auctions(session, model_id=model_id, limit=auctions)
    log = session.connection().execute(
        select(Review.decision, Review.inspector, Review.note, Review.at)
        .where(Review.model_id == model_id)
        .order_by(Review.id)
    )
    patron = None
    if row.auction_id is not None:  # one participant, one patron in an auction
        owner = select(ModelVersion.participant_id).where(ModelVersion.id == model_id)
        patron = session.connection().scalar(
            select(AuctionPatron.model_id)
            .join(ModelVersion, ModelVersion.id == AuctionPatron.model_id)
            .where(
                AuctionPatron.auction_id == row.auction_id,
                ModelVersion.participant_id == owner.scalar_subquery(),
            )
        )
    return dataclasses.replace(
        row,
        auctions=tuple(entered),
        reviews=tuple(ReviewEntry(*entry) for entry in log),
        patron_id=patron,
    )


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
    status: str
    inspected: bool
    """An inspector decided its status (admitted or refused it)."""
    appealed: bool
    """Its participant appealed the screener's refusal."""


_MODEL_SUMMARY = (
    select(
        ModelVersion.id,
        Participant.name,
        ModelVersion.version,
        ModelVersion.accepted,
        ModelVersion.manifest["description"].as_string(),
        ModelVersion.reasons,
        ModelVersion.created_at,
        ModelVersion.status,
        select(Review.id)
        .where(Review.model_id == ModelVersion.id, Review.decision.in_(("admit", "refuse")))
        .exists(),
        select(Review.id)
        .where(Review.model_id == ModelVersion.id, Review.decision == "appeal")
        .exists(),
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
    status: str | None = None,
) -> list[ModelSummary]:
    """Up to ``limit`` model versions with ids below ``before``, newest first, optionally of
    one participant, with one verdict and/or one status (one query)."""
    query = _MODEL_SUMMARY.limit(limit)
    if before is not None:
        query = query.where(ModelVersion.id < before)
    if participant is not None:
        query = query.where(Participant.id == _named(participant))
    if accepted is not None:
        query = query.where(ModelVersion.accepted.is_(accepted))
    if status is not None:
        query = query.where(ModelVersion.status == status)
    return [ModelSummary(*row) for row in session.connection().execute(query)]


@dataclass(frozen=True)
class Entry:
    """One auction a participant's model entered, and how that patron left it."""

    auction_id: int
    status: str
    """The auction's status."""
    model_id: int
    """The version that entered."""
    bidding_id: int | None
    """The version bidding now or at the end, after remote fine-tuning (None: ``model_id``)."""
    bought_at: float | None
    """The price it paid, if it bought."""
    bought_in: int | None
    quit_in: int | None
    """The iteration it bought or quit in."""


@dataclass(frozen=True)
class ParticipantView:
    """A participant: when it registered, how many versions it has, the newest of them, and the
    newest auctions its models entered."""

    name: str
    created_at: datetime
    n_versions: int
    versions: list[ModelSummary]
    entries: list[Entry]


def _entries(session: Session, *, participant_id: int, limit: int) -> list[Entry]:
    patron = AuctionPatron
    versions = (patron.model_id, patron.current_model_id)  # a purchase names the bidding one
    query = (
        select(
            patron.auction_id,
            Auction.status,
            patron.model_id,
            patron.current_model_id,
            Purchase.price,
            Purchase.iteration,
            Quit.iteration,
        )
        .join(ModelVersion, ModelVersion.id == patron.model_id)
        .join(Auction, Auction.id == patron.auction_id)
        .outerjoin(
            Purchase,
            (Purchase.auction_id == patron.auction_id) & Purchase.model_id.in_(versions),
        )
        .outerjoin(Quit, (Quit.auction_id == patron.auction_id) & Quit.model_id.in_(versions))
        .where(ModelVersion.participant_id == participant_id)
        .order_by(patron.auction_id.desc(), patron.position)
        .limit(limit)
    )
    return [Entry(*row) for row in session.connection().execute(query)]


def _named(name: str) -> ScalarSelect[int]:
    """The id of the participant a name names (``_naming``)."""
    where, first = _naming(name, participant_key(name))
    return select(Participant.id).where(where).order_by(first).limit(1).scalar_subquery()


def get_participant(session: Session, *, name: str, limit: int) -> ParticipantView | None:
    """A participant by name (compared as names are, ``participant_key``) with its ``limit``
    newest versions."""
    row = (
        session.connection()
        .execute(
            select(Participant.id, Participant.name, Participant.created_at).where(
                Participant.id == _named(name)
            )
        )
        .one_or_none()
    )
    if row is None:
        return None
    n_versions = session.connection().scalar(
        select(func.count()).where(ModelVersion.participant_id == row.id)
    )
    versions = list_models(session, before=None, limit=limit, participant=row.name)
    entries = _entries(session, participant_id=row.id, limit=limit)
    return ParticipantView(row.name, row.created_at, int(n_versions or 0), versions, entries)


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
