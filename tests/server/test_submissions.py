"""The group-commit writer behind POST /submit: one transaction per group, and the outcomes of
the submissions run one after another in arrival order."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from typing import Any

import pytest
from sqlalchemy import func, select

from screener import Reason, Verdict
from server import crud, submissions
from server.config import Settings
from server.db import Database, upgrade_schema
from server.models import ModelVersion, Participant, utcnow
from server.quotas import Limits
from server.submissions import Outcome, Refused, Stored, SubmissionWriter
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


async def _one_group(
    writer: SubmissionWriter, requests: list[tuple[str, Verdict, str | None]]
) -> list[Outcome]:
    """Queue every request before the writer thread starts, so they form a single group."""
    tasks = []
    for name, verdict, bearer in requests:
        manifest: dict[str, Any] = honest(name)
        tasks.append(
            asyncio.create_task(
                writer.store(
                    participant=name,
                    manifest=manifest,
                    verdict=verdict,
                    bearer=bearer,
                    address=None,
                )
            )
        )
    await asyncio.sleep(0)  # every task has queued its submission
    writer.start()
    try:
        return list(await asyncio.gather(*tasks))
    finally:
        writer.shutdown()


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


def test_a_group_behaves_like_the_submissions_in_arrival_order(database: Database) -> None:
    alice, bob = unique("alice"), unique("bob")
    writer = SubmissionWriter(database, LIMITS)
    outcomes = asyncio.run(
        _one_group(
            writer,
            [
                (alice, ACCEPTED, None),  # registers alice
                (alice, ACCEPTED, None),  # alice exists now: token needed
                (alice, ACCEPTED, "srdp_wrong"),  # wrong token
                (bob, REJECTED, None),  # a rejected model is stored too
            ],
        )
    )
    assert writer.groups == 1
    first, missing, wrong, rejected = outcomes
    assert isinstance(first, Stored) and first.version == 1 and first.token is not None
    assert isinstance(missing, Refused) and missing.status == 401
    assert missing.loc == ("header", "Authorization") and missing.kind == "missing_token"
    assert isinstance(wrong, Refused) and wrong.status == 403 and wrong.kind == "bad_token"
    assert isinstance(rejected, Stored) and rejected.version == 1
    assert _counts(database, alice) == (1, 1)  # the refused ones wrote nothing
    assert _counts(database, bob) == (1, 1)

    token = first.token
    again = SubmissionWriter(database, LIMITS)
    second, third = asyncio.run(
        _one_group(again, [(alice, ACCEPTED, token), (alice, REJECTED, token)])
    )
    assert isinstance(second, Stored) and (second.version, second.token) == (2, None)
    assert isinstance(third, Stored) and third.version == 3
    assert _counts(database, alice) == (1, 3)
    with database.session(write=False) as session:
        stored = crud.get_model(session, model_id=third.model_id)
    assert stored is not None and stored.accepted is False
    assert stored.reasons == [{"rule": "always_hold", "neuron": "B", "message": "never buys"}]


def test_a_unique_violation_refuses_only_the_submission_at_fault(
    database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another process took the name between our lookup and our insert: the group is rolled
    back and replayed one by one, and only that submission is answered 409."""
    taken, before, after = unique("taken"), unique("before"), unique("after")
    with database.session(write=True) as session:
        crud.insert_participants(
            session, rows=[{"name": taken, "token_hash": "0" * 64, "created_at": utcnow()}]
        )
        session.commit()
    real_lookup = crud.participants_by_names

    def blind_lookup(session: Any, *, names: list[str]) -> dict[str, crud.ParticipantRow]:
        return {n: p for n, p in real_lookup(session, names=names).items() if n != taken}

    monkeypatch.setattr(submissions.crud, "participants_by_names", blind_lookup)
    writer = SubmissionWriter(database, LIMITS)
    outcomes = asyncio.run(
        _one_group(
            writer, [(before, ACCEPTED, None), (taken, ACCEPTED, None), (after, ACCEPTED, None)]
        )
    )
    stored_before, conflict, stored_after = outcomes
    assert isinstance(stored_before, Stored) and isinstance(stored_after, Stored)
    assert isinstance(conflict, Refused) and conflict.status == 409
    assert conflict.loc == ("body", "participant") and conflict.kind == "conflict"
    assert _counts(database, before) == (1, 1)
    assert _counts(database, after) == (1, 1)
    assert _counts(database, taken) == (1, 0)


def test_a_stopped_writer_refuses_with_503(database: Database) -> None:
    writer = SubmissionWriter(database, LIMITS)
    writer.start()
    writer.shutdown()
    name = unique("late")
    outcome = asyncio.run(
        writer.store(
            participant=name, manifest=honest(name), verdict=ACCEPTED, bearer=None, address=None
        )
    )
    assert isinstance(outcome, Refused) and outcome.status == 503
    assert _counts(database, name) == (0, 0)
