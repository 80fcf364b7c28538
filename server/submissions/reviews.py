"""Human review of borderline models: the queue of held models, an inspector's decision, a
participant's appeal. Each runs in the request's session and commits once: a refused request
stores nothing."""

from __future__ import annotations

from collections.abc import Callable

from sqlalchemy.orm import Session

from server.api.errors import RequestError, api_error
from server.api.security import require_participant
from server.store import crud
from server.store.status import ModelStatus, ReviewDecision
from server.store.tables import utcnow
from server.submissions import quotas


def _missing(model_id: int) -> RequestError:
    return api_error(
        404, f"model {model_id} does not exist", loc=("path", "model_id"), kind="not_found"
    )


def _conflict(
    session: Session,
    model_id: int,
    unknown: str,
    rule: str,
    kind: str,
    said: Callable[[crud.ModelOwner, int], RequestError | None] | None = None,
) -> RequestError:
    """409 for a model no longer in the state a request needs (another request moved it first):
    nothing of this request is kept, and the message names the state the model is in now
    (``unknown`` if it is gone), or ``said`` says it (what the request would hear now)."""
    session.rollback()
    now = crud.model_owner(session, model_id=model_id)
    told = None if now is None or said is None else said(now, model_id)
    if told is not None:
        return told
    status = now.status if now else unknown
    return api_error(
        409, f"model {model_id} is {status}{rule}", loc=("path", "model_id"), kind=kind
    )


def _appealed_or_decided(owner: crud.ModelOwner, model_id: int) -> RequestError | None:
    """409 for a model an inspector refused (``decided``: final, appealed or not, the answer
    that says most) or appealed before (``appealed``), or None."""
    if owner.refused_by_inspector:
        return api_error(
            409,
            f"model {model_id} was refused by an inspector, whose refusal is final: "
            "only a model the screener refused is appealed",
            loc=("path", "model_id"),
            kind="decided",
        )
    if owner.appealed:
        return api_error(
            409,
            f"model {model_id} was appealed before: a model is appealed once",
            loc=("path", "model_id"),
            kind="appealed",
        )
    return None


def decide(
    session: Session, model_id: int, *, decision: ReviewDecision, inspector: str, note: str
) -> crud.StoredModel:
    """Admit or refuse a held model, logged with the evidence (404 if none, 409 if not held);
    the model as it now stands."""
    owner = crud.model_owner(session, model_id=model_id)
    if owner is None:
        raise _missing(model_id)
    now = utcnow()
    if not crud.decide(
        session,
        model_id=model_id,
        decision=decision,
        inspector=inspector,
        note=note,
        now=now,
    ):
        raise _conflict(
            session, model_id, "gone", ", not held: only a held model is decided", "not_held"
        )
    if decision == ReviewDecision.ADMIT:  # an accepted version now: its hold's cooldown ends
        quotas.record_admitted(session, participant=owner.participant, now=now)
    session.commit()
    return _view(session, model_id)


def appeal(
    session: Session,
    model_id: int,
    *,
    token: str | None,
    note: str,
    address: str | None,
    per_day: int,
) -> crud.StoredModel:
    """Send a model the screener refused back to the queue, once, with the participant's token
    (404 if no model, 401/403 without or with another token, 409 if accepted, held, appealed
    before or refused by an inspector, 429 past ``per_day`` appeals from ``address``);
    the model as it now stands."""
    owner = crud.model_owner(session, model_id=model_id)
    if owner is None:
        raise _missing(model_id)
    if token is None:
        raise api_error(
            401,
            f"appeals need the token of participant {owner.participant!r}: "
            "'Authorization: Bearer <token>'",
            loc=("header", "Authorization"),
            kind="missing_token",
        )
    require_participant(token, owner.token_hash, owner.participant)
    settled = _appealed_or_decided(owner, model_id)
    if settled is not None:
        raise settled
    now = utcnow()
    if owner.status == ModelStatus.REFUSED:
        throttled = quotas.appeal_throttle(session, address=address, per_day=per_day, now=now)
        if throttled is not None:
            raise api_error(
                429,
                throttled.msg,
                loc=("path", "model_id"),
                kind="quota",
                headers={"Retry-After": str(throttled.retry_after_s)},
            )
    if owner.status != ModelStatus.REFUSED or not crud.appeal(
        session, model_id=model_id, participant=owner.participant, note=note, now=now
    ):
        raise _conflict(  # another appeal or a decision first: said as a moment later
            session,
            model_id,
            owner.status,
            ": only a refused model is appealed",
            "not_refused",
            _appealed_or_decided,
        )
    quotas.record_appeal(session, address=address, now=now)
    session.commit()
    return _view(session, model_id)


def _view(session: Session, model_id: int) -> crud.StoredModel:
    view = crud.get_model_view(session, model_id=model_id, auctions=0)
    assert view is not None
    return view
