"""The uploads of remote rounds: what an upload is checked against (``upload_target``), and its
writes: stored on arrival (``store_upload``, in the transaction of that read), then its verdict
(``record_verdict``), or marked late (``record_late``).

The read and the store share one write transaction, so the store acts on what the read saw:
the round still open and the upload before its deadline, the patron's answer so far. On
PostgreSQL the read takes the auction's rounds ``FOR SHARE`` (the step's closing ``UPDATE``
waits for the uploads in flight, and the uploads after it see the round closed); SQLite
serialises writers anyway.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import (
    Connection,
    Text,
    bindparam,
    cast,
    func,
    insert,
    literal_column,
    select,
    update,
)
from sqlalchemy.orm import Session, aliased

from screener import Verdict, review, with_hold_reasons
from server.store.crud.live import notify_change, notify_due
from server.store.crud.steps import PendingUploadsError, close_round, round_answers
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
    auction_status: str
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
    answer: dict[str, Any] | None = None
    """The answer's body as stored (for a repeat of a judged upload)."""


class UploadLookupError(LookupError):
    """The auction or the model of an upload's path does not exist (``field`` names which)."""

    def __init__(self, field: str) -> None:
        super().__init__(field)
        self.field = field


_CURRENT = aliased(ModelVersion)
"""The version a patron bids with now (the path's model for a model that is not a patron)."""
_HEAD = (
    select(
        Auction.fine_tune_mode,
        Auction.status.label("auction_status"),
        Participant.name,
        Participant.token_hash,
        AuctionPatron.position,
        _CURRENT.id.label("current_id"),
        _CURRENT.version.label("current_version"),
        _CURRENT.manifest,
    )
    .select_from(Auction)
    .join(ModelVersion, ModelVersion.id == bindparam("model_id"))
    .join(Participant, Participant.id == ModelVersion.participant_id)
    .outerjoin(
        AuctionPatron,
        (AuctionPatron.auction_id == Auction.id) & (AuctionPatron.model_id == ModelVersion.id),
    )
    .join(_CURRENT, _CURRENT.id == func.coalesce(AuctionPatron.current_model_id, ModelVersion.id))
    .where(Auction.id == bindparam("auction_id"))
)
"""What the path names: the auction, the model and its participant, its patron's place."""
_TARGET = (
    _HEAD.add_columns(
        FineTuneRound.id.label("round_id"),
        FineTuneRound.status,
        FineTuneRound.deadline,
        FineTuneRound.asked,
        FineTuneAnswer.id.label("answer_id"),
        FineTuneAnswer.outcome,
        FineTuneAnswer.body_sha256,
        FineTuneAnswer.answer,
    )
    .join(
        FineTuneRound,
        (FineTuneRound.auction_id == Auction.id) & (FineTuneRound.round == bindparam("round")),
    )
    .outerjoin(
        FineTuneAnswer,
        (FineTuneAnswer.round_id == FineTuneRound.id)
        & (FineTuneAnswer.position == AuctionPatron.position),
    )
    .where(AuctionPatron.position.is_not(None))
    .with_for_update(read=True, of=FineTuneRound)
)
"""Everything an upload by a patron to an existing round is checked against, in one row."""
_AUCTION_EXISTS = select(Auction.id).where(Auction.id == bindparam("auction_id"))
_NEWEST_ROUND = (
    select(FineTuneRound.round, FineTuneRound.status)
    .where(FineTuneRound.auction_id == bindparam("auction_id"))
    .order_by(FineTuneRound.round.desc())
    .limit(1)
)


def upload_target(
    connection: Connection, *, auction_id: int, model_id: int, round_number: int
) -> UploadTarget | UploadLookupError:
    """What an upload to ``round_number`` of ``auction_id`` for ``model_id`` is checked
    against, in the write transaction that stores it (``store_upload``): one query for a patron
    of an auction that has the round (more, to name the problem, for any other path; the
    UploadLookupError of a path that names no auction or model)."""
    ids = {"auction_id": auction_id, "model_id": model_id, "round": round_number}
    row = connection.execute(_TARGET, ids).one_or_none()
    head, newest = row, None
    if head is None:  # no such round, or not a patron: read what names the problem
        head = connection.execute(_HEAD, ids).one_or_none()
        if head is None:
            exists = connection.execute(_AUCTION_EXISTS, ids).first() is not None
            return UploadLookupError("model_id" if exists else "auction_id")
        newest = connection.execute(_NEWEST_ROUND, ids).one_or_none()
    return UploadTarget(
        fine_tune_mode=head.fine_tune_mode,
        auction_status=head.auction_status,
        position=head.position,
        participant=head.name,
        token_hash=head.token_hash,
        current_id=head.current_id,
        current_version=head.current_version,
        current_manifest=head.manifest,
        newest_round=None if newest is None else newest.round,
        newest_status=None if newest is None else newest.status,
        round_id=None if row is None else row.round_id,
        round_status=None if row is None else row.status,
        deadline=None if row is None else row.deadline,
        asked=[] if row is None else list(row.asked),
        answer_outcome=None if row is None else row.outcome,
        answer_sha256=None if row is None else row.body_sha256,
        answer_id=None if row is None else row.answer_id,
        answer=None if row is None else row.answer,
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


def _late(number: int, *, cancelled: bool) -> tuple[int, str, str]:
    why = "closed: the auction was cancelled" if cancelled else "closed or past its deadline"
    return (410, f"round {number} is {why}; the upload is late and was not applied", "round_closed")


_INSERT_ANSWER = insert(FineTuneAnswer).returning(FineTuneAnswer.id)


def store_upload(connection: Connection, *, upload: UploadIn, target: UploadTarget) -> Stored:
    """Store an upload as it arrives, in the transaction that read its ``target``: pending
    with its manifest (a repeat of the current weights is accepted at once), a repeat of an
    answered upload (the same bytes: the route refuses others) answered as before, a late one
    recorded as late (in a cancelled auction too: its 410 names the cancel)."""
    if target.answer_outcome in ANSWERED:
        if target.answer_outcome == AnswerOutcome.PENDING:
            return Stored(answer_id=target.answer_id)
        return Stored(answer=answer_bytes(target.answer or {}))
    if target.round_status != RoundStatus.OPEN or (
        target.deadline is not None and upload.arrived >= target.deadline
    ):
        record_late(connection, upload=upload, missing_id=target.answer_id)
        cancelled = target.auction_status == AuctionStatus.CANCELLED
        return Stored(refusal=_late(upload.round_number, cancelled=cancelled))
    row: dict[str, Any] = {
        "round_id": upload.round_id,
        "position": upload.position,
        "model_id": upload.current_id,
        "uploaded_id": None,
        "body_sha256": upload.body_sha256,
        "bytes_in": upload.bytes_in,
        "created_at": upload.arrived,
    }
    late_before = target.answer_id if target.answer_outcome == AnswerOutcome.LATE else None
    if upload.manifest is not None:
        row.update(outcome=AnswerOutcome.PENDING, manifest=upload.manifest, bytes_out=0)
        return Stored(answer_id=_write_answer(connection, row, late_before))
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
    _write_answer(connection, row, late_before)
    return Stored(answer=body)


def _write_answer(connection: Connection, row: dict[str, Any], late_id: int | None) -> int:
    """Insert the answer ``row``, or make the patron's late answer ``late_id`` this one: an
    upload judged late at its arrival, whose round's deadline a database outage then pushed
    back (``push_back_deadlines``), may come again in time."""
    if late_id is None:
        answer_id: int = connection.execute(_INSERT_ANSWER, row).scalar_one()
        return answer_id
    connection.execute(
        update(FineTuneAnswer)
        .where(FineTuneAnswer.id == late_id, FineTuneAnswer.outcome == AnswerOutcome.LATE)
        .values(**row)
    )
    return late_id


def record_late(connection: Connection, *, upload: UploadIn, missing_id: int | None) -> None:
    """Mark a late upload: a new late answer, or the patron's missing answer made late."""
    if missing_id is not None:
        connection.execute(
            update(FineTuneAnswer)
            .where(FineTuneAnswer.id == missing_id, FineTuneAnswer.outcome == AnswerOutcome.MISSING)
            .values(
                outcome=AnswerOutcome.LATE, body_sha256=upload.body_sha256, bytes_in=upload.bytes_in
            )
        )
        return
    connection.execute(
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
    round_id: int = 0


def left_pending(session: Session, *, auction_id: int | None = None) -> list[PendingUpload]:
    """The uploads still pending in rounds already closed (a cancel or a failure closes a
    round whatever its uploads), oldest first; of ``auction_id`` only, if given."""
    query = (
        select(FineTuneAnswer.id, FineTuneAnswer.manifest, FineTuneAnswer.round_id)
        .join(FineTuneRound, FineTuneRound.id == FineTuneAnswer.round_id)
        .where(
            FineTuneAnswer.outcome == AnswerOutcome.PENDING,
            FineTuneRound.status == RoundStatus.CLOSED,
        )
    )
    if auction_id is not None:
        query = query.where(FineTuneRound.auction_id == auction_id)
    rows = session.connection().execute(query.order_by(FineTuneAnswer.id))
    return [PendingUpload(row.id, row.manifest, row.round_id) for row in rows]


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
        cast(FineTuneAnswer.manifest, Text).label("manifest"),  # stored again as it is
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
_INSERT_VERSION = (
    insert(ModelVersion)
    .values(
        version=select(func.max(ModelVersion.version) + 1)
        .where(ModelVersion.participant_id == bindparam("owner"))
        .scalar_subquery()
    )
    .returning(ModelVersion.id, ModelVersion.version)
)
"""The participant's next version (after its latest; a judged upload's participant has one)."""
_JUDGE_ANSWER = (
    update(FineTuneAnswer).where(FineTuneAnswer.id == bindparam("answer_id")).values(manifest=None)
)
"""Sets the answer's verdict (the columns the parameters name) and drops its manifest."""
_JUDGED = (
    select(func.count())
    .select_from(FineTuneAnswer)
    .where(
        FineTuneAnswer.round_id == bindparam("round_id"),
        FineTuneAnswer.outcome.in_([literal_column(f"'{outcome}'") for outcome in JUDGED]),
    )
)
"""The round's judged answers (the outcomes written in the SQL: no list to expand per call)."""
_DUE_AT = (
    update(Auction)
    .where(Auction.id == bindparam("auction_id"), Auction.status == AuctionStatus.RUNNING)
    .values(
        next_step_at=bindparam("now", type_=Auction.next_step_at.type),
        # the round's close is a change of the auction for live updates, which read this
        updated_at=bindparam("now", type_=Auction.updated_at.type),
    )
)


@dataclass(frozen=True)
class Judged:
    """What ``record_verdict`` did: the answer's bytes, and whether this call judged the upload
    (False: another request or process had, and its answer stands) and accepted it."""

    answer: bytes
    judged: bool
    accepted: bool = False


def record_verdict(
    connection: Connection, *, answer_id: int, verdict: Verdict, margin: float, now: datetime
) -> Judged:
    """A pending upload judged: its manifest stored as the participant's next version
    (accepted, refused, or held for an inspector within ``margin`` of a bar: then, as refused,
    the previous version bids on), its answer written. An upload already judged (by another
    request or process) keeps its answer, which is returned, not judged again."""
    row = connection.execute(_PENDING_FOR_UPDATE, {"answer_id": answer_id}).one_or_none()
    if row is None:  # judged by a concurrent request while this one waited for the row's lock:
        # PostgreSQL re-checks the locked row, now naming a version this statement cannot see
        stored = select(FineTuneAnswer.answer).where(FineTuneAnswer.id == answer_id)
        return Judged(answer_bytes(connection.execute(stored).scalar_one() or {}), False)
    if row.outcome != AnswerOutcome.PENDING:
        return Judged(answer_bytes(row.answer or {}), False)
    if row.manifest is None:  # stored with every pending upload
        raise RuntimeError(f"the pending upload {answer_id} has no manifest")
    if connection.dialect.name != "sqlite":  # SQLite has no row locks: it serialises writers
        connection.execute(_LOCK_PARTICIPANT, {"id": row.participant_id})
    status = ModelStatus(review(verdict, margin))
    reasons = [reason.to_dict() for reason in with_hold_reasons(verdict, margin).reasons]
    accepted = status == ModelStatus.ACCEPTED
    version = {
        "owner": row.participant_id,
        "participant_id": row.participant_id,
        "manifest": JSONText(row.manifest),
        "accepted": accepted,
        "status": status,
        "reasons": reasons,
        "evidence": [e.to_dict() for e in verdict.evidence],
        "created_at": now,
        "parent_id": row.model_id,
        "auction_id": row.auction_id,
        "round": row.round,
    }
    uploaded, number = connection.execute(_INSERT_VERSION, version).one()
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
    judged = {
        "answer_id": answer_id,
        "outcome": outcome,
        "uploaded_id": uploaded,
        "model_id": uploaded if accepted else row.model_id,
        "answer": JSONText(body.decode()),
        "bytes_out": len(body),
    }
    connection.execute(_JUDGE_ANSWER, judged)
    return Judged(body, True, accepted)


_JUDGED_ANSWER = select(FineTuneAnswer.outcome, FineTuneAnswer.answer).where(
    FineTuneAnswer.id == bindparam("answer_id")
)


def judged_answer(connection: Connection, *, answer_id: int) -> bytes | None:
    """The answer's bytes once the upload ``answer_id`` is judged (by any process); None while
    it is pending."""
    row = connection.execute(_JUDGED_ANSWER, {"answer_id": answer_id}).one()
    return None if row.outcome == AnswerOutcome.PENDING else answer_bytes(row.answer or {})


_ROUND_FOR_UPDATE = (
    select(FineTuneRound.auction_id, FineTuneRound.asked, FineTuneRound.status)
    .where(FineTuneRound.id == bindparam("round_id"))
    .with_for_update()
)


def close_when_answered(connection: Connection, *, round_id: int, now: datetime) -> bool:
    """Close the round at ``now`` if every asked patron's upload is judged (none pending): its
    accepted versions bid from now, and its auction is due at once for the step that plays on.
    Whether it closed it."""
    key = {"round_id": round_id}
    # The round's row lock serialises the last verdicts of a round: each counts the others'
    # (under READ COMMITTED two that commit together would each miss the other's).
    head = connection.execute(_ROUND_FOR_UPDATE, key).one()
    if head.status != RoundStatus.OPEN:
        return False
    if connection.execute(_JUDGED, key).scalar_one() < len(head.asked):
        return False
    try:  # none pending (then the close below cannot fail); else its step closes it
        round_answers(connection, round_id)
    except PendingUploadsError:
        return False
    if not connection.execute(_DUE_AT, {"auction_id": head.auction_id, "now": now}).rowcount:
        return False  # the auction ended meanwhile (cancelled)
    auction_id = head.auction_id
    close_round(connection, auction_id=auction_id, round_id=round_id, asked=head.asked, now=now)
    notify_change(connection, kind="auction", row_id=auction_id)
    notify_due(connection, kind="auction")  # the step that plays on, on any replica
    return True
