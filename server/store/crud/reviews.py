"""Held models and their audit log: the review queue (oldest first), an inspector's decision on
a held model, a participant's appeal of a refused one. Each write is conditional on the status
it changes, so two inspectors (or two appeals) racing on one model write once."""

from __future__ import annotations

from dataclasses import dataclass, replace
from datetime import datetime
from typing import Any

from sqlalchemy import Exists, and_, func, insert, select, update
from sqlalchemy.orm import Session

from server.store.crud.lists import keyset
from server.store.status import ModelStatus, ReviewDecision
from server.store.tables import ModelVersion, Participant, Review


@dataclass(frozen=True)
class HeldModel:
    """A model waiting for an inspector, with what the screener measured."""

    id: int
    participant: str
    version: int
    reasons: list[dict[str, str]]
    evidence: list[dict[str, Any]] | None
    created_at: datetime
    auction_id: int | None
    round: int | None
    appeal: str | None
    """The participant's note when it came to the queue by appeal."""
    participant_id: int
    newer: tuple[tuple[int, int, str], ...] = ()
    """The participant's later versions (id, version, status), newest first, at most
    ``NEWER_SHOWN``: what deciding this one leaves bidding."""


NEWER_SHOWN = 10
"""Later versions of its participant listed with a held model."""

_HELD = (
    select(
        ModelVersion.id,
        Participant.name,
        ModelVersion.version,
        ModelVersion.reasons,
        ModelVersion.evidence,
        ModelVersion.created_at,
        ModelVersion.auction_id,
        ModelVersion.round,
        Review.note,
        ModelVersion.participant_id,
    )
    .join(Participant, Participant.id == ModelVersion.participant_id)
    .outerjoin(
        Review,
        and_(Review.model_id == ModelVersion.id, Review.decision == ReviewDecision.APPEAL),
    )
    .where(ModelVersion.status == ModelStatus.HELD)
)


def held_models(session: Session, *, after: int | None, limit: int) -> list[HeldModel]:
    """Up to ``limit`` held models with ids above ``after``, oldest first, each with its
    participant's later versions, at most ``NEWER_SHOWN`` (two queries)."""
    query = keyset(_HELD, ModelVersion.id, cursor=after, order="oldest").limit(limit)
    held = [HeldModel(*row) for row in session.connection().execute(query)]
    if not held:
        return held
    newest = (  # each participant's newest NEWER_SHOWN versions: the later ones are among them
        select(
            ModelVersion.participant_id,
            ModelVersion.id,
            ModelVersion.version,
            ModelVersion.status,
            func.row_number()
            .over(partition_by=ModelVersion.participant_id, order_by=ModelVersion.version.desc())
            .label("rank"),
        )
        .where(ModelVersion.participant_id.in_({h.participant_id for h in held}))
        .subquery()
    )
    later = session.connection().execute(
        select(newest.c.participant_id, newest.c.id, newest.c.version, newest.c.status)
        .where(newest.c.rank <= NEWER_SHOWN)
        .order_by(newest.c.version.desc())
    )
    by_participant: dict[int, list[tuple[int, int, str]]] = {}
    for participant_id, model_id, version, status in later:
        by_participant.setdefault(participant_id, []).append((model_id, version, status))
    return [
        replace(
            h,
            newer=tuple(v for v in by_participant.get(h.participant_id, []) if v[1] > h.version),
        )
        for h in held
    ]


@dataclass(frozen=True)
class ModelOwner:
    """Who a model belongs to and where its verdict stands."""

    participant: str
    token_hash: str
    status: str
    appealed: bool
    participant_id: int
    refused_by_inspector: bool


def model_owner(session: Session, *, model_id: int) -> ModelOwner | None:
    """A model's participant, token hash, status, whether it was appealed and whether an
    inspector refused it (one query)."""

    def logged(decision: ReviewDecision) -> Exists:
        return (
            select(Review.id)
            .where(Review.model_id == ModelVersion.id, Review.decision == decision)
            .exists()
        )

    row = (
        session.connection()
        .execute(
            select(
                Participant.name,
                Participant.token_hash,
                ModelVersion.status,
                logged(ReviewDecision.APPEAL),
                ModelVersion.participant_id,
                logged(ReviewDecision.REFUSE),
            )
            .join(Participant, Participant.id == ModelVersion.participant_id)
            .where(ModelVersion.id == model_id)
        )
        .one_or_none()
    )
    return None if row is None else ModelOwner(*row)


def _log(
    session: Session, *, model_id: int, decision: str, inspector: str, note: str, now: datetime
) -> None:
    """Append to the model's audit log, with the evidence stored with the model."""
    evidence = session.connection().scalar(
        select(ModelVersion.evidence).where(ModelVersion.id == model_id)
    )
    session.connection().execute(
        insert(Review),
        {
            "model_id": model_id,
            "decision": decision,
            "inspector": inspector,
            "note": note,
            "at": now,
            "evidence": evidence,
        },
    )


def decide(
    session: Session,
    *,
    model_id: int,
    decision: ReviewDecision,
    inspector: str,
    note: str,
    now: datetime,
) -> bool:
    """An inspector's decision on a held model: admitted (accepted) or refused, logged; False
    (nothing written) if the model is not held."""
    status = ModelStatus.ACCEPTED if decision == ReviewDecision.ADMIT else ModelStatus.REFUSED
    moved = session.connection().execute(
        update(ModelVersion)
        .where(ModelVersion.id == model_id, ModelVersion.status == ModelStatus.HELD)
        .values(status=status, accepted=status == ModelStatus.ACCEPTED)
    )
    if moved.rowcount != 1:
        return False
    _log(session, model_id=model_id, decision=decision, inspector=inspector, note=note, now=now)
    return True


def appeal(session: Session, *, model_id: int, participant: str, note: str, now: datetime) -> bool:
    """A refused model, never appealed, back to the queue (held), logged; False (nothing
    written) otherwise."""
    appealed = (
        select(Review.id)
        .where(Review.model_id == model_id, Review.decision == ReviewDecision.APPEAL)
        .exists()
    )
    moved = session.connection().execute(
        update(ModelVersion)
        .where(ModelVersion.id == model_id, ModelVersion.status == ModelStatus.REFUSED, ~appealed)
        .values(status=ModelStatus.HELD)
    )
    if moved.rowcount != 1:
        return False
    _log(
        session,
        model_id=model_id,
        decision=ReviewDecision.APPEAL,
        inspector=participant,
        note=note,
        now=now,
    )
    return True
