"""The upload writer: the checked uploads of ``PUT .../rounds/{round}/models/{model_id}`` (and
of the round sockets) stored in group commits, and the published-bytes counters.

``UploadWriter`` runs in the screening process (``server.screening``), which gathers a round's
uploads as they come, re-screens the new versions among them in one batch and hands the group
to ``UploadWriter.write_group``: ONE transaction, re-checking there, against the database, that each
round is still open and before its deadline (a round closed meanwhile makes the upload late)
and that the patron has not answered the round yet, then a ring of the rounds' doorbells for
their workers. On PostgreSQL the rounds are read ``FOR SHARE``: the worker's closing ``UPDATE``
waits for the uploads in flight, and the uploads that come after it see the round closed. The
API process writes nothing for an upload: its event loop parses and checks.

``PublishedBytes`` (in the API process) adds the bytes of published round answers (counted by
the round watcher) to their rounds' ``bytes_published``, at least every ``FLUSH_S``.
"""

from __future__ import annotations

import json
import logging
import threading
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Literal

from sqlalchemy import bindparam, insert, select, update
from sqlalchemy.orm import Session

from screener import Verdict
from server import crud, doorbell
from server.db import Database, JSONText, is_database_outage, unavailable_message
from server.grouping import GroupTransaction
from server.models import FineTuneAnswer, FineTuneRound, Participant, utcnow
from server.status import ANSWERED, AnswerOutcome, RoundStatus

log = logging.getLogger("srd.rounds")

FLUSH_S = 0.2
"""Published-bytes counters are written at least this often while they grow."""

UploadKind = Literal["version", "unchanged", "late"]


@dataclass(frozen=True)
class UploadRequest:
    """An upload that passed the route's checks, to be stored (or found late)."""

    kind: UploadKind
    """version: store the manifest as a new version (accepted or refused by ``verdict``);
    unchanged: the patron's current weights, acknowledged without a new version; late: past
    the deadline or closed, only marked."""
    round_number: int
    round_id: int
    position: int
    participant_id: int
    current_id: int
    current_version: int
    auction_id: int
    body_sha256: str
    bytes_in: int
    manifest: JSONText | None = None
    """The new version's manifest as stored (its ``model_dump_json``)."""
    verdict: Verdict | None = None


@dataclass(frozen=True)
class Answered:
    """The upload's answer, exactly the bytes sent (repeats get the same bytes)."""

    body: bytes


@dataclass(frozen=True)
class UploadRefused:
    """An error answer: status, message, the location it names, the error type."""

    status: int
    msg: str
    loc: tuple[str | int, ...]
    kind: str


UploadOutcome = Answered | UploadRefused


def _late(request: UploadRequest) -> UploadRefused:
    return UploadRefused(
        410,
        f"round {request.round_number} is closed or past its deadline: the upload is late "
        "and was not applied",
        ("path", "round"),
        "round_closed",
    )


def _different(request: UploadRequest) -> UploadRefused:
    return UploadRefused(
        409,
        f"this patron already answered round {request.round_number} with another body: one "
        "upload per round",
        ("path", "round"),
        "already_answered",
    )


def answer_bytes(answer: dict[str, Any]) -> bytes:
    """The JSON bytes of an upload's answer (compact; a stored answer gives the same bytes)."""
    return json.dumps(answer, separators=(",", ":"), allow_nan=False).encode()


_INSERT_ANSWERS = insert(FineTuneAnswer.__table__)  # type: ignore[arg-type]
"""Core (not the ORM's bulk path): a group's answers in one multi-row statement."""


def _conflict(request: UploadRequest) -> UploadRefused:
    return UploadRefused(
        409,
        "the upload was written concurrently with another; retry",
        ("path", "round"),
        "conflict",
    )


def _unavailable(exc: Exception) -> UploadRefused:
    return UploadRefused(503, unavailable_message(exc), ("database",), "db_unavailable")


_Rows = dict[Any, Any]
"""Rows of one query (SQLAlchemy ``Row`` objects), keyed as the decisions look them up."""


@dataclass
class _Plan:
    """A group's uploads decided in arrival order: their answers and the rows to write."""

    rounds: _Rows
    """round id → its status and deadline, read ``FOR SHARE``"""
    stored: _Rows
    """(round id, position) → the answer stored before this group"""
    next_version: dict[int, int]
    """participant id → the number its next version takes"""
    now: datetime
    outcomes: list[UploadOutcome | None] = field(default_factory=list)
    """One per upload; None until its answer is written (or copied, for a repeat)."""
    decided: dict[tuple[int, int], tuple[str, int]] = field(default_factory=dict)
    """(round id, position) → body sha and index of the upload that answers it in this group"""
    repeats: list[tuple[int, int]] = field(default_factory=list)
    """(index, index of the same upload earlier in the group)"""
    versions: list[dict[str, Any]] = field(default_factory=list)
    """Model version rows to insert"""
    answers: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    """(index, answer row to insert)"""
    lates: list[tuple[UploadRequest, int | None]] = field(default_factory=list)
    """Late uploads to record, with the id of the patron's missing answer if there is one"""

    def decide(self, index: int, item: UploadRequest) -> UploadOutcome | None:
        """The upload's answer if known now; None for one written below (or a repeat)."""
        key = (item.round_id, item.position)
        if key in self.decided:
            sha, first = self.decided[key]
            if sha != item.body_sha256:
                return _different(item)
            self.repeats.append((index, first))
            return None
        stored = self.stored.get(key)
        if stored is not None and stored.outcome in ANSWERED:
            same = stored.body_sha256 == item.body_sha256
            return Answered(answer_bytes(stored.answer or {})) if same else _different(item)
        if self._is_late(item):
            if stored is None or stored.outcome == AnswerOutcome.MISSING:
                self.lates.append((item, None if stored is None else stored.id))
            return _late(item)
        self.answers.append((index, self._answer_row(item)))
        self.decided[key] = (item.body_sha256, index)
        return None

    def _is_late(self, item: UploadRequest) -> bool:
        current = self.rounds.get(item.round_id)
        return (
            item.kind == "late"
            or current is None
            or current.status != RoundStatus.OPEN
            or self.now >= current.deadline
        )

    def _answer_row(self, item: UploadRequest) -> dict[str, Any]:
        """The answer row of an upload in time (its new version, if any, queued to insert)."""
        answer: dict[str, Any] = {
            "round": item.round_number,
            "accepted": True,
            "reasons": [],
            "version": item.current_version,
            "model_id": item.current_id,
            "parent_id": item.current_id,
            "uploaded_id": None,
        }
        row: dict[str, Any] = {
            "round_id": item.round_id,
            "position": item.position,
            "outcome": AnswerOutcome.ACCEPTED,
            "model_id": item.current_id,
            "uploaded_id": None,
            "body_sha256": item.body_sha256,
            "bytes_in": item.bytes_in,
            "created_at": self.now,
        }
        if item.kind == "version":
            assert item.manifest is not None and item.verdict is not None
            number = self.next_version[item.participant_id]
            self.next_version[item.participant_id] = number + 1
            accepted = item.verdict.accepted
            answer.update(
                accepted=accepted,
                reasons=[reason.to_dict() for reason in item.verdict.reasons],
            )
            row["outcome"] = AnswerOutcome.ACCEPTED if accepted else AnswerOutcome.REFUSED
            self.versions.append(
                {
                    "participant_id": item.participant_id,
                    "version": number,
                    "manifest": item.manifest,
                    "accepted": accepted,
                    "reasons": answer["reasons"],
                    "created_at": self.now,
                    "parent_id": item.current_id,
                    "auction_id": item.auction_id,
                    "round": item.round_number,
                }
            )
            row["_version_number"] = number
        answer["outcome"] = row["outcome"]
        row["answer"] = answer
        return row


def _store_group(session: Session, group: list[UploadRequest]) -> list[UploadOutcome]:
    """Decide the group's uploads in arrival order against the database and write them."""
    plan = _Plan(
        rounds=_rounds_for_share(session, group),
        stored=_stored_answers(session, group),
        next_version=_next_versions(session, group),
        now=utcnow(),
    )
    for index, item in enumerate(group):
        plan.outcomes.append(plan.decide(index, item))
    _write_answers(session, plan)
    _record_lates(session, plan)
    outcomes = [outcome for outcome in plan.outcomes if outcome is not None]
    assert len(outcomes) == len(group), "every upload of the group is answered"
    return outcomes


_ROUNDS_FOR_SHARE = (
    select(FineTuneRound.id, FineTuneRound.status, FineTuneRound.deadline)
    .where(FineTuneRound.id.in_(bindparam("rounds", expanding=True)))
    .with_for_update(read=True)
)
_STORED_ANSWERS = select(
    FineTuneAnswer.id,
    FineTuneAnswer.round_id,
    FineTuneAnswer.position,
    FineTuneAnswer.outcome,
    FineTuneAnswer.body_sha256,
    FineTuneAnswer.answer,
).where(
    FineTuneAnswer.round_id.in_(bindparam("rounds", expanding=True)),
    FineTuneAnswer.position.in_(bindparam("positions", expanding=True)),
)
_LOCK_PARTICIPANTS = (
    select(Participant.id)
    .where(Participant.id.in_(bindparam("ids", expanding=True)))
    .with_for_update()
)
# Built once: a group's queries differ only in their parameters.


def _rounds_for_share(session: Session, group: list[UploadRequest]) -> _Rows:
    rounds = sorted({item.round_id for item in group})
    return {
        row.id: row for row in session.connection().execute(_ROUNDS_FOR_SHARE, {"rounds": rounds})
    }


def _stored_answers(session: Session, group: list[UploadRequest]) -> _Rows:
    parameters = {
        "rounds": sorted({item.round_id for item in group}),
        "positions": sorted({item.position for item in group}),
    }
    return {
        (row.round_id, row.position): row
        for row in session.connection().execute(_STORED_ANSWERS, parameters)
    }


def _next_versions(session: Session, group: list[UploadRequest]) -> dict[int, int]:
    """The next version number of each participant uploading a new version, taken under the
    participants' row locks."""
    participants = sorted({item.participant_id for item in group if item.kind == "version"})
    if participants:
        session.connection().execute(_LOCK_PARTICIPANTS, {"ids": participants})
    latest = crud.latest_versions(session, participant_ids=participants)
    return {participant_id: version + 1 for participant_id, version in latest.items()}


def _write_answers(session: Session, plan: _Plan) -> None:
    """Insert the group's new versions, then its answers, each with its final bytes."""
    version_ids = iter(crud.insert_model_versions(session, rows=plan.versions))
    inserted = []
    for index, row in plan.answers:
        answer = row["answer"]
        number = row.pop("_version_number", None)
        if number is not None:
            uploaded = next(version_ids)
            row["uploaded_id"] = answer["uploaded_id"] = uploaded
            if answer["accepted"]:
                row["model_id"] = answer["model_id"] = uploaded
                answer["version"] = number
        body = answer_bytes(answer)
        row["bytes_out"] = len(body)
        row["answer"] = JSONText(body.decode())  # stored as the bytes sent
        plan.outcomes[index] = Answered(body)
        inserted.append(row)
    for index, first in plan.repeats:
        plan.outcomes[index] = plan.outcomes[first]
    if inserted:
        session.connection().execute(_INSERT_ANSWERS, inserted)


def _record_lates(session: Session, plan: _Plan) -> None:
    """Mark the late uploads: a new late answer, or the patron's missing answer made late."""
    for item, answer_id in plan.lates:
        if answer_id is None:
            session.connection().execute(
                _INSERT_ANSWERS,
                [
                    {
                        "round_id": item.round_id,
                        "position": item.position,
                        "outcome": AnswerOutcome.LATE,
                        "model_id": item.current_id,
                        "body_sha256": item.body_sha256,
                        "bytes_in": item.bytes_in,
                        "bytes_out": 0,
                        "created_at": plan.now,
                    }
                ],
            )
        else:
            session.execute(
                update(FineTuneAnswer)
                .where(
                    FineTuneAnswer.id == answer_id,
                    FineTuneAnswer.outcome == AnswerOutcome.MISSING,
                )
                .values(
                    outcome=AnswerOutcome.LATE, body_sha256=item.body_sha256, bytes_in=item.bytes_in
                )
            )


class UploadWriter(GroupTransaction[UploadRequest, UploadOutcome]):
    """``write_group(group)``: a group of uploads, already grouped by the caller (the screening
    process), decided and written in one transaction (see the module docstring)."""

    def __init__(self, database: Database) -> None:
        self._bells = doorbell.scope(database.url)
        super().__init__(
            "upload-writer",
            database,
            _store_group,
            conflict=_conflict,
            unavailable=_unavailable,
            after_commit=self._ring,
        )

    def _ring(self, group: list[UploadRequest]) -> None:
        """Wake the workers waiting on the group's rounds (``server.auctions``)."""
        for round_id in sorted({item.round_id for item in group}):
            doorbell.ring(self._bells, doorbell.round_bell(round_id))


class PublishedBytes:
    """``count(round_id, n_bytes)`` from any thread: added to the round's ``bytes_published`` by
    one thread at least every ``FLUSH_S`` while counts grow (and once more at ``shutdown``)."""

    def __init__(self, database: Database) -> None:
        self._database = database
        self._counts: dict[int, int] = defaultdict(int)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="published-bytes", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def shutdown(self) -> None:
        """Write what is counted, then stop the thread."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def count(self, round_id: int, n_bytes: int) -> None:
        """Add to a round's published-bytes counter (written within ``FLUSH_S``)."""
        with self._lock:
            self._counts[round_id] += n_bytes

    def _run(self) -> None:
        while not self._stop.wait(FLUSH_S):
            self._flush()
        self._flush()

    def _flush(self) -> None:
        with self._lock:
            counts, self._counts = dict(self._counts), defaultdict(int)
        if not counts:
            return
        try:
            with self._database.session(write=True) as session:
                crud.add_published_bytes(session, counts=counts)
                session.commit()
        except Exception as exc:  # counted again at the next flush
            if not is_database_outage(exc):
                raise
            log.warning("published-bytes counters not written: %s", unavailable_message(exc))
            with self._lock:
                for round_id, n_bytes in counts.items():
                    self._counts[round_id] += n_bytes
