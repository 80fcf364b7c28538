"""The write path of ``POST /submit``: a screened manifest stored as its participant's next
version, in one transaction on a thread of the pool.

Quotas (``server.submissions.quotas``) are decided in the same transaction. ``precheck`` asks
the same questions (name, token, quotas) before the route spends screening on a submission; the
answer given at ``store`` is the authoritative one.

Names are compared after NFKC and case folding (``server.store.tables.participant_key``): a
name that is a stored one but for case or Unicode form is refused (409, taken). A refused submission
(taken name, missing or wrong token, over a quota) writes nothing. A unique name or version
taken meanwhile by another process is answered 409 (retry); a database outage is the global
503 (``server.api.errors``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from screener import Verdict
from server.api.security import hash_token, new_token, token_matches
from server.store import crud
from server.store.db import Database
from server.store.status import ModelStatus
from server.store.tables import participant_key, utcnow
from server.submissions import quotas

log = logging.getLogger("srd.submissions")

PRUNE_EVERY_S = 600.0  # how often old quota events are deleted


@dataclass(frozen=True)
class Stored:
    """A stored model version."""

    model_id: int
    participant: str
    version: int
    token: str | None
    """The new participant's token (first version only), else None."""


@dataclass(frozen=True)
class Refused:
    """A submission answered with an error; nothing of it is stored."""

    status: int
    msg: str
    loc: tuple[str, ...]
    kind: str
    retry_after_s: int | None = None
    """For 429 and 503: when to try again (the ``Retry-After`` header)."""


Outcome = Stored | Refused


@dataclass
class _Submission:
    """A screened manifest to store, or (``verdict`` None) a question asked before screening:
    would this participant's submission be refused for its token or a quota?"""

    participant: str
    manifest: dict[str, Any] | None
    verdict: Verdict | None
    bearer: str | None
    address: str | None
    status: ModelStatus = ModelStatus.REFUSED
    """The verdict under review (``screener.review``)."""


@dataclass
class _Known:
    """A participant as the group sees it: stored (``id``) or registered earlier in the group."""

    name: str
    token_hash: str
    next_version: int
    id: int | None = None


def _name_refusal(item: _Submission, participant: _Known | None) -> Refused | None:
    """A name that is another participant's but for case or Unicode form."""
    if participant is None or participant.name == item.participant:
        return None
    return Refused(
        409,
        f"the name {item.participant!r} is taken: participant {participant.name!r} has it "
        "(names are compared ignoring case and Unicode form)",
        ("body", "participant"),
        "name_taken",
    )


def _token_refusal(item: _Submission, participant: _Known | None) -> Refused | None:
    """A later version without the participant's token (a new name needs none)."""
    if participant is None:
        return None
    if item.bearer is None:
        return Refused(
            401,
            f"participant {item.participant!r} exists: send its token as "
            "'Authorization: Bearer <token>'",
            ("header", "Authorization"),
            "missing_token",
        )
    if not token_matches(item.bearer, participant.token_hash):
        return Refused(
            403,
            f"the bearer token is not the token of participant {item.participant!r}",
            ("header", "Authorization"),
            "bad_token",
        )
    return None


def _refusal(
    item: _Submission, participant: _Known | None, throttle: quotas.Throttle
) -> Refused | None:
    """Why the submission is refused now (its name, its token, then the quotas), if it is."""
    refusal = _name_refusal(item, participant) or _token_refusal(item, participant)
    if refusal is not None:
        return refusal
    throttled = throttle.check(
        participant=item.participant, address=item.address, new=participant is None
    )
    if throttled is None:
        return None
    return Refused(429, throttled.msg, ("body", "participant"), "quota", throttled.retry_after_s)


def _store_group(
    session: Session, group: list[_Submission], limits: quotas.Limits
) -> list[Outcome | None]:
    """Every submission of the group, decided in arrival order, then written with one query
    and two multi-row inserts, whatever the group's size. Questions (no verdict) are answered
    with the refusal their submission would get now, or None; they write nothing."""
    existing = crud.participants_by_names(
        session, names=list(dict.fromkeys(item.participant for item in group))
    )
    latest = crud.latest_versions(session, participant_ids=[p.id for p in existing.values()])
    known: dict[str, _Known] = {}  # by name, then by name key for the names not stored
    for stored in existing.values():
        known[stored.name] = _Known(
            stored.name, stored.token_hash, latest.get(stored.id, 0) + 1, stored.id
        )
    for stored in existing.values():
        known.setdefault(stored.name_key, known[stored.name])
    now = utcnow()
    throttle = quotas.Throttle(
        session,
        limits,
        now,
        quotas.subjects([i.participant for i in group], [i.address for i in group]),
    )
    new_participants: list[dict[str, Any]] = []
    versions: list[tuple[int, str, int, str | None]] = []  # group index, name, version, token
    outcomes: list[Outcome | None] = []
    for index, item in enumerate(group):
        participant = known.get(item.participant) or known.get(participant_key(item.participant))
        refusal = _refusal(item, participant, throttle)
        if refusal is not None or item.verdict is None:
            outcomes.append(refusal)
            continue
        token: str | None = None
        if participant is None:
            token = new_token(crud.PARTICIPANT_TOKEN_PREFIX)
            participant = _Known(item.participant, hash_token(token), 1)
            known[item.participant] = known[participant_key(item.participant)] = participant
            new_participants.append(
                {"name": item.participant, "token_hash": participant.token_hash, "created_at": now}
            )
        throttle.record(
            participant=item.participant,
            address=item.address,
            new=token is not None,
            accepted=item.status == ModelStatus.ACCEPTED,
        )
        versions.append((index, item.participant, participant.next_version, token))
        participant.next_version += 1
        outcomes.append(None)  # stored: filled in below
    new_ids = crud.insert_participants(session, rows=new_participants)
    for row, participant_id in zip(new_participants, new_ids, strict=True):
        known[row["name"]].id = participant_id
    rows = []
    for index, name, version, _ in versions:
        verdict = group[index].verdict
        assert verdict is not None
        rows.append(
            {
                "participant_id": known[name].id,
                "version": version,
                "manifest": group[index].manifest,
                "accepted": group[index].status == ModelStatus.ACCEPTED,
                "status": group[index].status,
                "reasons": [reason.to_dict() for reason in verdict.reasons],
                "evidence": [e.to_dict() for e in verdict.evidence],
                "created_at": now,
            }
        )
    model_ids = crud.insert_model_versions(session, rows=rows)
    for (index, name, version, token), model_id in zip(versions, model_ids, strict=True):
        outcomes[index] = Stored(model_id, name, version, token)
    throttle.write(session)
    return outcomes


def _conflict(item: _Submission) -> Refused:
    return Refused(
        409,
        f"participant {item.participant!r} was written concurrently; retry",
        ("body", "participant"),
        "conflict",
    )


class SubmissionWriter:
    """``await store(...)`` and ``await precheck(...)`` from any event loop; each runs one
    transaction on a thread of the pool."""

    def __init__(self, database: Database, limits: quotas.Limits) -> None:
        self._database = database
        self._limits = limits
        self._pruned_at = -math.inf

    async def store(
        self,
        *,
        participant: str,
        manifest: dict[str, Any],
        verdict: Verdict,
        status: ModelStatus,
        bearer: str | None,
        address: str | None,
    ) -> Outcome:
        """Store one screened manifest as the participant's next version, with its verdict
        under review (or refuse it)."""
        item = _Submission(participant, manifest, verdict, bearer, address, status)
        outcome = await run_in_threadpool(self._write, item)
        assert outcome is not None
        return outcome

    async def precheck(
        self, *, participant: str, bearer: str | None, address: str | None
    ) -> Refused | None:
        """The refusal (name, token, quota) a submission of ``participant`` would get now, if
        any: asked before screening, so refused requests cost no screening."""
        item = _Submission(participant, None, None, bearer, address)
        outcome = await run_in_threadpool(self._ask, item)
        assert not isinstance(outcome, Stored)
        return outcome

    def _ask(self, item: _Submission) -> Outcome | None:
        with self._database.session(write=False) as session:
            return _store_group(session, [item], self._limits)[0]

    def _write(self, item: _Submission) -> Outcome | None:
        try:
            with self._database.session(write=True) as session:
                (outcome,) = _store_group(session, [item], self._limits)
                session.commit()
        except IntegrityError:
            return _conflict(item)
        self._prune()
        return outcome

    def _prune(self) -> None:
        """Now and then, forget the quota events no limit counts any more."""
        if time.monotonic() - self._pruned_at < PRUNE_EVERY_S:
            return
        self._pruned_at = time.monotonic()
        try:
            with self._database.session(write=True) as session:
                quotas.prune(session, utcnow())
                session.commit()
        except Exception:
            log.exception("pruning the quota events failed")
