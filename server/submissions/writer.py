"""The write path of ``POST /submit``: a screened manifest stored as its participant's next
version, in one transaction on a thread of the pool.

Quotas (``server.submissions.quotas``) are decided in the same transaction. ``precheck`` asks
the same questions (name, token, quotas) before the route spends screening on a submission; the
answer given at ``store`` is the authoritative one.

Names are compared after NFKC and case folding, look-alike characters made one
(``server.store.tables.participant_key``): a name that is a stored one but for case, Unicode
form or look-alikes is refused (409, taken; its owner, by its
token, is told the registered spelling: 422). A refused submission
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
from server.store.tables import utcnow
from server.submissions import quotas

log = logging.getLogger("srd.submissions")

PRUNE_EVERY_S = 600.0  # how often old quota events are deleted
WRITE_TRIES = 3
"""Transactions a submission's write is tried in when concurrent ones win its unique keys."""


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


COMPARED = (
    "(names are compared ignoring case, Unicode form and look-alike characters: I, l and 1; "
    "O and 0; rn and m; vv and w; cl and d; -, _ and .)"
)


def _name_refusal(item: _Submission, participant: crud.ParticipantRow | None) -> Refused | None:
    """A name that is a registered participant's but for case, Unicode form or look-alike
    characters: its owner (its token) is told the registered spelling; anyone else that the
    name is taken."""
    if participant is None or participant.name == item.participant:
        return None
    if item.bearer is not None and token_matches(item.bearer, participant.token_hash):
        return Refused(
            422,
            f"your participant is spelled {participant.name!r}, not {item.participant!r}: "
            f"write it so {COMPARED}",
            ("body", "participant"),
            "name_spelling",
        )
    return Refused(
        409,
        f"the name {item.participant!r} is taken: participant {participant.name!r} has it "
        f"{COMPARED}",
        ("body", "participant"),
        "name_taken",
    )


def _token_refusal(item: _Submission, participant: crud.ParticipantRow | None) -> Refused | None:
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


def _store(session: Session, item: _Submission, limits: quotas.Limits) -> Outcome | None:
    """The submission decided (its name, its token, then the quotas) and, if it has a verdict
    and is not refused, written as the participant's next version. A question (no verdict) is
    answered with the refusal its submission would get now, or None; it writes nothing."""
    participant = crud.participant_by_name(session, name=item.participant)
    refusal = _name_refusal(item, participant) or _token_refusal(item, participant)
    if refusal is not None:
        return refusal
    if item.verdict is not None and item.address is not None:  # counts that decide a write:
        crud.lock_subject(session, quotas.address_subject(item.address))  # none racing them
    now = utcnow()
    throttle = quotas.Throttle(
        session, limits, now, participant=item.participant, address=item.address
    )
    throttled = throttle.check(new=participant is None)
    if throttled is not None:
        return Refused(
            429, throttled.msg, ("body", "participant"), "quota", throttled.retry_after_s
        )
    if item.verdict is None:
        return None
    token: str | None = None
    if participant is None:
        token = new_token(crud.PARTICIPANT_TOKEN_PREFIX)
        participant_id = crud.insert_participant(
            session, name=item.participant, token_hash=hash_token(token), now=now
        )
        version = 1
    else:
        participant_id = participant.id
        version = crud.latest_version(session, participant_id=participant_id) + 1
    accepted = item.status == ModelStatus.ACCEPTED
    model_id = crud.insert_model_version(
        session,
        values={
            "participant_id": participant_id,
            "version": version,
            "manifest": item.manifest,
            "accepted": accepted,
            "status": item.status,
            "reasons": [reason.to_dict() for reason in item.verdict.reasons],
            "evidence": [e.to_dict() for e in item.verdict.evidence],
            "created_at": now,
        },
    )
    throttle.record(session, new=token is not None, accepted=accepted)
    return Stored(model_id, item.participant, version, token)


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
            return _store(session, item, self._limits)

    def _write(self, item: _Submission) -> Outcome | None:
        """One transaction; tried again when a concurrent one wrote the same name or version
        first (a unique key refused it), so it is decided on what that one wrote: the name now
        registered asks for its token (401) or is taken (409 ``name_taken``), the next version
        number is free. ``conflict`` (409) only if that happens ``WRITE_TRIES`` times."""
        for _ in range(WRITE_TRIES):
            try:
                with self._database.session(write=True) as session:
                    outcome = _store(session, item, self._limits)
                    session.commit()
            except IntegrityError:
                continue
            self._prune()
            return outcome
        return _conflict(item)

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
