"""The writer behind POST /submit: one transaction per submission; names, tokens and versions
decided against what is stored, and a name taken meanwhile by another process answered 409."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from typing import Any

import pytest
from sqlalchemy import func, select

from screener import Reason, Verdict
from server.config import Settings
from server.store import crud
from server.store.db import Database, upgrade_schema
from server.store.status import ModelStatus
from server.store.tables import ModelVersion, Participant, utcnow
from server.submissions import writer as submissions
from server.submissions.quotas import Limits
from server.submissions.writer import Outcome, Refused, Stored, SubmissionWriter
from tests.support.factories import honest, unique
from tests.support.server import QUOTAS_OFF

ACCEPTED = Verdict(accepted=True)
REJECTED = Verdict(accepted=False, reasons=[Reason("always_hold", "B", "never buys")])
LIMITS = Limits.of(Settings(**QUOTAS_OFF))


@pytest.fixture
def database(database_url: str) -> Iterator[Database]:
    upgrade_schema(database_url)
    db = Database(database_url)
    yield db
    db.close()


def _store(writer: SubmissionWriter, name: str, verdict: Verdict, bearer: str | None) -> Outcome:
    return asyncio.run(
        writer.store(
            participant=name,
            manifest=honest(name),
            verdict=verdict,
            status=ModelStatus.ACCEPTED if verdict.accepted else ModelStatus.REFUSED,
            bearer=bearer,
            address=None,
        )
    )


def _counts(database: Database, name: str) -> tuple[int, int]:
    with database.session(write=False) as session:
        participants = session.scalar(
            select(func.count()).select_from(Participant).where(Participant.name == name)
        )
        versions = session.scalar(
            select(func.count())
            .select_from(ModelVersion)
            .join(Participant)
            .where(Participant.name == name)
        )
    return int(participants or 0), int(versions or 0)


def test_submissions_are_decided_against_what_is_stored(database: Database) -> None:
    writer = SubmissionWriter(database, LIMITS)
    alice = unique("alice")
    first = _store(writer, alice, ACCEPTED, None)
    assert isinstance(first, Stored) and first.version == 1 and first.token is not None
    token = first.token
    second = _store(writer, alice, REJECTED, token)
    assert isinstance(second, Stored) and second.version == 2 and second.token is None
    missing = _store(writer, alice, ACCEPTED, None)
    assert isinstance(missing, Refused) and missing.status == 401
    wrong = _store(writer, alice, ACCEPTED, "srdp_not-the-token")
    assert isinstance(wrong, Refused) and wrong.status == 403
    folded = _store(writer, alice.upper(), ACCEPTED, None)
    assert isinstance(folded, Refused) and folded.status == 409 and folded.kind == "name_taken"
    spelt = _store(writer, alice.upper(), ACCEPTED, token)  # its owner: how it is spelt
    assert isinstance(spelt, Refused) and spelt.status == 422 and spelt.kind == "name_spelling"
    assert _counts(database, alice) == (1, 2)
    with database.session(write=False) as session:
        stored = crud.get_model(session, model_id=second.model_id)
    assert stored is not None and stored.accepted is False
    assert stored.reasons == [{"rule": "always_hold", "neuron": "B", "message": "never buys"}]


def test_a_name_registered_meanwhile_is_answered_as_a_registered_name_is(
    database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two first submissions of one new name at once (two replicas): the one whose insert
    loses is decided again on what the other wrote, 401 without its token (as it would be a
    moment later), not a ``conflict`` whose retry would get that 401 anyway."""
    name = unique("raced")
    with database.session(write=True) as session:
        crud.insert_participant(session, name=name, token_hash="0" * 64, now=utcnow())
        session.commit()
    looked = crud.participant_by_name
    lookups: list[str] = []

    def late_lookup(session: Any, *, name: str) -> crud.ParticipantRow | None:
        lookups.append(name)  # the first read ran before the other's commit
        return None if len(lookups) == 1 else looked(session, name=name)

    monkeypatch.setattr(submissions.crud, "participant_by_name", late_lookup)
    answer = _store(SubmissionWriter(database, LIMITS), name, ACCEPTED, None)
    assert isinstance(answer, Refused) and (answer.status, answer.kind) == (401, "missing_token")
    assert _counts(database, name) == (1, 0) and len(lookups) == 2


def test_a_name_taken_meanwhile_is_answered_409_and_stores_nothing(
    database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another process took the name between our lookup and our insert, every time it was
    tried: 409 ``conflict``."""
    taken, other = unique("taken"), unique("other")
    with database.session(write=True) as session:
        crud.insert_participant(session, name=taken, token_hash="0" * 64, now=utcnow())
        session.commit()

    def blind_lookup(session: Any, *, name: str) -> crud.ParticipantRow | None:
        return None  # as if the name were free

    monkeypatch.setattr(submissions.crud, "participant_by_name", blind_lookup)
    writer = SubmissionWriter(database, LIMITS)
    conflict = _store(writer, taken, ACCEPTED, None)
    assert isinstance(conflict, Refused) and conflict.status == 409
    assert conflict.loc == ("body", "participant") and conflict.kind == "conflict"
    assert _counts(database, taken) == (1, 0)
    assert isinstance(_store(writer, other, ACCEPTED, None), Stored)
