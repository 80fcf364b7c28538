"""The uploads of remote rounds: what an upload is checked against (read for a batch of uploads
at once), and its writes: stored on arrival (``store_upload``), then its verdict
(``record_verdict``), or marked late (``record_late``).

Every write re-checks, in its own transaction, what the route checked from its read: the round
is still open and the upload arrived before its deadline, the patron has not answered yet. On
PostgreSQL the round is read ``FOR SHARE`` (the step's closing ``UPDATE`` waits for the uploads
in flight, and the uploads after it see the round closed); SQLite serialises writers anyway.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import bindparam, func, insert, select, update
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Session

from screener import Verdict, review
from server.store.crud.live import notify_change
from server.store.crud.models import insert_model_versions, latest_versions
from server.store.db import JSONText
from server.store.status import (
    ANSWERED,
    JUDGED,
    AnswerOutcome,
    AuctionStatus,
    ModelStatus,
    RoundStatus,
)
from server.store.tables import (
    Auction,
    AuctionPatron,
    FineTuneAnswer,
    FineTuneRound,
    ModelVersion,
    Participant,
)


@dataclass(frozen=True)
class UploadTarget:
    """What ``PUT /auctions/{id}/rounds/{round}/models/{model_id}`` checks before screening."""

    fine_tune_mode: str
    position: int | None
    """The model's position among the auction's patrons (None: not a patron)."""
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
    answer_id: int | None = None


class UploadLookupError(LookupError):
    """The auction or the model of an upload's path does not exist (``field`` names which)."""

    def __init__(self, field: str) -> None:
        super().__init__(field)
        self.field = field


UploadKey = tuple[int, int, int]
"""(auction id, model id, round) of an upload's path."""


_Rows = dict[Any, Any]
"""Rows of one query of the batch (SQLAlchemy ``Row`` objects), keyed as the lookups need."""


@dataclass(frozen=True)
class _Batch:
    """Everything a batch of uploads is checked against, read once for the whole batch."""

    auctions: _Rows
    """auction id → fine-tuning mode"""
    owners: _Rows
    """model id → its participant"""
    patrons: _Rows
    """(auction id, model id) → the patron's position and current version id"""
    versions: _Rows
    """model id → version number and manifest (of the versions patrons bid with now)"""
    rounds: dict[int, _Rows]
    """auction id → round number → the round"""
    answers: _Rows
    """(round id, position) → the patron's answer so far"""


def upload_targets(
    session: Session, *, keys: Sequence[UploadKey]
) -> list[UploadTarget | UploadLookupError]:
    """What each upload of a batch is checked against, read in one transaction with six
    queries whatever the batch's size (the UploadLookupError of a path that names no auction
    or model)."""
    connection = session.connection()
    auction_ids = sorted({a for a, _, _ in keys})
    model_ids = sorted({m for _, m, _ in keys})
    auctions = _auctions(connection, auction_ids)
    owners = _owners(connection, model_ids)
    patrons = _patrons(connection, auction_ids, model_ids)
    versions = _versions(connection, sorted({_current_of(patrons, a, m) for a, m, _ in keys}))
    rounds = _rounds(connection, auction_ids)
    asked_ids = sorted({r.id for a, _, n in keys if (r := rounds.get(a, {}).get(n))})
    positions = sorted({p.position for p in patrons.values()})
    answers = _answers(connection, asked_ids, positions)
    batch = _Batch(auctions, owners, patrons, versions, rounds, answers)
    return [_target(batch, key) for key in keys]


_AUCTIONS = select(Auction.id, Auction.fine_tune_mode).where(
    Auction.id.in_(bindparam("auction_ids", expanding=True))
)
_OWNERS = (
    select(ModelVersion.id, Participant.name, Participant.token_hash)
    .join(Participant, Participant.id == ModelVersion.participant_id)
    .where(ModelVersion.id.in_(bindparam("model_ids", expanding=True)))
)
_PATRONS = select(
    AuctionPatron.auction_id,
    AuctionPatron.model_id,
    AuctionPatron.position,
    AuctionPatron.current_model_id,
).where(
    AuctionPatron.auction_id.in_(bindparam("auction_ids", expanding=True)),
    AuctionPatron.model_id.in_(bindparam("model_ids", expanding=True)),
)
_VERSIONS = select(ModelVersion.id, ModelVersion.version, ModelVersion.manifest).where(
    ModelVersion.id.in_(bindparam("version_ids", expanding=True))
)
_ROUNDS = select(
    FineTuneRound.id,
    FineTuneRound.auction_id,
    FineTuneRound.round,
    FineTuneRound.status,
    FineTuneRound.deadline,
    FineTuneRound.asked,
).where(FineTuneRound.auction_id.in_(bindparam("auction_ids", expanding=True)))
_ANSWERS = select(
    FineTuneAnswer.id,
    FineTuneAnswer.round_id,
    FineTuneAnswer.position,
    FineTuneAnswer.outcome,
    FineTuneAnswer.body_sha256,
).where(
    FineTuneAnswer.round_id.in_(bindparam("round_ids", expanding=True)),
    FineTuneAnswer.position.in_(bindparam("positions", expanding=True)),
)


def _auctions(connection: Connection, auction_ids: list[int]) -> _Rows:
    return {row.id: row for row in connection.execute(_AUCTIONS, {"auction_ids": auction_ids})}


def _owners(connection: Connection, model_ids: list[int]) -> _Rows:
    return {row.id: row for row in connection.execute(_OWNERS, {"model_ids": model_ids})}


def _patrons(connection: Connection, auction_ids: list[int], model_ids: list[int]) -> _Rows:
    rows = connection.execute(_PATRONS, {"auction_ids": auction_ids, "model_ids": model_ids})
    return {(row.auction_id, row.model_id): row for row in rows}


def _current_of(patrons: _Rows, auction_id: int, model_id: int) -> int:
    """The id of the version the patron bids with now (the path's model when not a patron)."""
    patron = patrons.get((auction_id, model_id))
    if patron is None or patron.current_model_id is None:
        return model_id
    current: int = patron.current_model_id
    return current


def _versions(connection: Connection, version_ids: list[int]) -> _Rows:
    return {row.id: row for row in connection.execute(_VERSIONS, {"version_ids": version_ids})}


def _rounds(connection: Connection, auction_ids: list[int]) -> dict[int, _Rows]:
    rounds: dict[int, _Rows] = {}
    for row in connection.execute(_ROUNDS, {"auction_ids": auction_ids}):
        rounds.setdefault(row.auction_id, {})[row.round] = row
    return rounds


def _answers(connection: Connection, round_ids: list[int], positions: list[int]) -> _Rows:
    rows = connection.execute(_ANSWERS, {"round_ids": round_ids, "positions": positions})
    return {(row.round_id, row.position): row for row in rows}


def _target(batch: _Batch, key: UploadKey) -> UploadTarget | UploadLookupError:
    """One upload's target, from the rows of its batch."""
    auction_id, model_id, number = key
    auction, owner = batch.auctions.get(auction_id), batch.owners.get(model_id)
    if auction is None or owner is None:
        return UploadLookupError("auction_id" if auction is None else "model_id")
    patron = batch.patrons.get((auction_id, model_id))
    current = batch.versions[_current_of(batch.patrons, auction_id, model_id)]
    mine = batch.rounds.get(auction_id, {})
    newest = mine[max(mine)] if mine else None
    asked = mine.get(number)
    answer = None
    if asked is not None and patron is not None:
        answer = batch.answers.get((asked.id, patron.position))
    return UploadTarget(
        fine_tune_mode=auction.fine_tune_mode,
        position=None if patron is None else patron.position,
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
        answer_id=None if answer is None else answer.id,
    )


def answer_bytes(answer: dict[str, Any]) -> bytes:
    """The JSON bytes of an upload's answer (compact; a stored answer gives the same bytes)."""
    return json.dumps(answer, separators=(",", ":"), allow_nan=False).encode()


@dataclass(frozen=True)
class UploadIn:
    """An upload that passed the route's checks, as ``store_upload`` writes it."""

    round_number: int
    round_id: int
    position: int
    current_id: int
    current_version: int
    body_sha256: str
    bytes_in: int
    arrived: datetime
    """When its body was read: the deadline is judged at this moment."""
    manifest: JSONText | None
    """The new manifest; None when it repeats the patron's current weights."""


@dataclass(frozen=True)
class Stored:
    """What ``store_upload`` did: ``answer`` is the body to send (None while pending, then
    ``answer_id`` awaits its verdict); ``refusal`` an error (status, message, kind)."""

    answer: bytes | None = None
    answer_id: int | None = None
    refusal: tuple[int, str, str] | None = None


def _late(number: int) -> tuple[int, str, str]:
    return (
        410,
        f"round {number} is closed or past its deadline: the upload is late and was not applied",
        "round_closed",
    )


def _different(number: int) -> tuple[int, str, str]:
    return (
        409,
        f"this patron already answered round {number} with another body: one upload per round",
        "already_answered",
    )


_ROUND_FOR_SHARE = (
    select(FineTuneRound.status, FineTuneRound.deadline)
    .where(FineTuneRound.id == bindparam("round_id"))
    .with_for_update(read=True)
)
_ANSWER_OF = select(
    FineTuneAnswer.id, FineTuneAnswer.outcome, FineTuneAnswer.body_sha256, FineTuneAnswer.answer
).where(
    FineTuneAnswer.round_id == bindparam("round_id"), FineTuneAnswer.position == bindparam("at")
)


def store_upload(session: Session, *, upload: UploadIn) -> Stored:
    """Store an upload as it arrives: pending with its manifest (a repeat of the current
    weights is accepted at once), after re-checking the round and the patron's answer."""
    connection = session.connection()
    key = {"round_id": upload.round_id, "at": upload.position}
    current = connection.execute(_ROUND_FOR_SHARE, key).one()
    stored = connection.execute(_ANSWER_OF, key).one_or_none()
    if stored is not None and stored.outcome in ANSWERED:
        if stored.body_sha256 != upload.body_sha256:
            return Stored(refusal=_different(upload.round_number))
        if stored.outcome == AnswerOutcome.PENDING:
            return Stored(answer_id=stored.id)
        return Stored(answer=answer_bytes(stored.answer or {}))
    if current.status != RoundStatus.OPEN or upload.arrived >= current.deadline:
        record_late(session, upload=upload, missing_id=None if stored is None else stored.id)
        return Stored(refusal=_late(upload.round_number))
    row: dict[str, Any] = {
        "round_id": upload.round_id,
        "position": upload.position,
        "model_id": upload.current_id,
        "uploaded_id": None,
        "body_sha256": upload.body_sha256,
        "bytes_in": upload.bytes_in,
        "created_at": upload.arrived,
    }
    if upload.manifest is not None:
        row.update(outcome=AnswerOutcome.PENDING, manifest=upload.manifest, bytes_out=0)
        answer_id = connection.execute(
            insert(FineTuneAnswer).returning(FineTuneAnswer.id), row
        ).scalar_one()
        return Stored(answer_id=answer_id)
    body = answer_bytes(
        {
            "round": upload.round_number,
            "accepted": True,
            "reasons": [],
            "version": upload.current_version,
            "model_id": upload.current_id,
            "parent_id": upload.current_id,
            "uploaded_id": None,
            "outcome": AnswerOutcome.ACCEPTED,
        }
    )
    row.update(outcome=AnswerOutcome.ACCEPTED, answer=JSONText(body.decode()), bytes_out=len(body))
    connection.execute(insert(FineTuneAnswer), row)
    return Stored(answer=body)


def record_late(session: Session, *, upload: UploadIn, missing_id: int | None) -> None:
    """Mark a late upload: a new late answer, or the patron's missing answer made late."""
    if missing_id is not None:
        session.execute(
            update(FineTuneAnswer)
            .where(FineTuneAnswer.id == missing_id, FineTuneAnswer.outcome == AnswerOutcome.MISSING)
            .values(
                outcome=AnswerOutcome.LATE, body_sha256=upload.body_sha256, bytes_in=upload.bytes_in
            )
        )
        return
    session.execute(
        insert(FineTuneAnswer),
        {
            "round_id": upload.round_id,
            "position": upload.position,
            "outcome": AnswerOutcome.LATE,
            "model_id": upload.current_id,
            "body_sha256": upload.body_sha256,
            "bytes_in": upload.bytes_in,
            "bytes_out": 0,
            "created_at": upload.arrived,
        },
    )


@dataclass(frozen=True)
class PendingUpload:
    """An upload awaiting its verdict: its answer row and the manifest to judge."""

    answer_id: int
    manifest: dict[str, Any]


def pending_uploads(
    session: Session, *, round_id: int | None = None, answer_id: int | None = None
) -> list[PendingUpload]:
    """The pending uploads of a round (or the one answer ``answer_id``, if still pending)."""
    query = select(FineTuneAnswer.id, FineTuneAnswer.manifest).where(
        FineTuneAnswer.outcome == AnswerOutcome.PENDING
    )
    if round_id is not None:
        query = query.where(FineTuneAnswer.round_id == round_id)
    if answer_id is not None:
        query = query.where(FineTuneAnswer.id == answer_id)
    rows = session.connection().execute(query.order_by(FineTuneAnswer.id))
    return [PendingUpload(row.id, row.manifest) for row in rows]


_PENDING_FOR_UPDATE = (
    select(
        FineTuneAnswer.id,
        FineTuneAnswer.outcome,
        FineTuneAnswer.answer,
        FineTuneAnswer.model_id,
        FineTuneAnswer.manifest,
        FineTuneRound.auction_id,
        FineTuneRound.round,
        ModelVersion.participant_id,
        ModelVersion.version,
    )
    .join(FineTuneRound, FineTuneRound.id == FineTuneAnswer.round_id)
    .join(ModelVersion, ModelVersion.id == FineTuneAnswer.model_id)
    .where(FineTuneAnswer.id == bindparam("answer_id"))
    .with_for_update(of=FineTuneAnswer)
)
_LOCK_PARTICIPANT = (
    select(Participant.id).where(Participant.id == bindparam("id")).with_for_update()
)


def record_verdict(
    session: Session, *, answer_id: int, verdict: Verdict, margin: float, now: datetime
) -> bytes:
    """A pending upload judged: its manifest stored as the participant's next version
    (accepted, refused, or held for an inspector within ``margin`` of a bar: then, as refused,
    the previous version bids on), its answer written; the answer's bytes. An upload already
    judged (by another process) keeps its answer, which is returned."""
    connection = session.connection()
    row = connection.execute(_PENDING_FOR_UPDATE, {"answer_id": answer_id}).one()
    if row.outcome != AnswerOutcome.PENDING:
        return answer_bytes(row.answer or {})
    if connection.dialect.name != "sqlite":  # SQLite has no row locks: it serialises writers
        connection.execute(_LOCK_PARTICIPANT, {"id": row.participant_id})
    number = latest_versions(session, participant_ids=[row.participant_id])[row.participant_id] + 1
    reasons = [reason.to_dict() for reason in verdict.reasons]
    status = ModelStatus(review(verdict, margin))
    accepted = status == ModelStatus.ACCEPTED
    (uploaded,) = insert_model_versions(
        session,
        rows=[
            {
                "participant_id": row.participant_id,
                "version": number,
                "manifest": row.manifest,
                "accepted": accepted,
                "status": status,
                "reasons": reasons,
                "evidence": [e.to_dict() for e in verdict.evidence],
                "created_at": now,
                "parent_id": row.model_id,
                "auction_id": row.auction_id,
                "round": row.round,
            }
        ],
    )
    outcome = AnswerOutcome(status)
    body = answer_bytes(
        {
            "round": row.round,
            "accepted": accepted,
            "reasons": reasons,
            "version": number if accepted else row.version,
            "model_id": uploaded if accepted else row.model_id,
            "parent_id": row.model_id,
            "uploaded_id": uploaded,
            "outcome": outcome,
        }
    )
    connection.execute(
        update(FineTuneAnswer)
        .where(FineTuneAnswer.id == answer_id)
        .values(
            outcome=outcome,
            uploaded_id=uploaded,
            model_id=uploaded if accepted else row.model_id,
            answer=JSONText(body.decode()),
            bytes_out=len(body),
            manifest=None,
        )
    )
    return body


_ROUND_FOR_UPDATE = (
    select(FineTuneRound.auction_id, FineTuneRound.asked, FineTuneRound.status)
    .where(FineTuneRound.id == bindparam("round_id"))
    .with_for_update()
)
_JUDGED = (
    select(func.count())
    .select_from(FineTuneAnswer)
    .where(
        FineTuneAnswer.round_id == bindparam("round_id"),
        FineTuneAnswer.outcome.in_(JUDGED),
    )
)
_DUE_AT = (
    update(Auction)
    .where(Auction.id == bindparam("auction_id"), Auction.status == AuctionStatus.RUNNING)
    .values(next_step_at=bindparam("now", type_=Auction.next_step_at.type))
)


def due_when_answered(session: Session, *, round_id: int, now: datetime) -> bool:
    """Make the round's auction due for its next step at ``now`` if every asked patron's
    upload is judged (none pending); whether it did."""
    connection = session.connection()
    key = {"round_id": round_id}
    # The round's row lock serialises the last verdicts of a round: each counts the others'
    # (under READ COMMITTED two that commit together would each miss the other's).
    head = connection.execute(_ROUND_FOR_UPDATE, key).one()
    if head.status != RoundStatus.OPEN:
        return False
    judged = connection.execute(_JUDGED, key).scalar_one()
    if judged < len(head.asked):
        return False
    moved = connection.execute(_DUE_AT, {"auction_id": head.auction_id, "now": now})
    if not moved.rowcount:
        return False
    notify_change(session, kind="auction", row_id=head.auction_id)
    return True
