"""Quotas and rate limits on POST /submit: answered 429 with Retry-After and the limit named,
nothing stored, counted in the database (so every API process sharing it sees the same)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.store.tables import ModelVersion, Participant, RateEvent
from tests.server.test_remote_protocol import (
    first_asked_upload,
    open_round,
    put,
    remote_auction,
    start_remote,
)
from tests.support.databases import postgres_admin_url, throwaway_postgres
from tests.support.factories import honest, saboteur, unique
from tests.support.processes import descendants, process_name
from tests.support.server import count, make_settings


def quota_app(tmp_path, database_url: str | None = None, **limits: Any) -> TestClient:
    url = database_url or f"sqlite:///{tmp_path / 'srd.db'}"
    settings = make_settings(url, tmp_path / "data")
    return TestClient(create_app(settings.model_copy(update=limits)))


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def assert_throttled(response: Any, setting: str) -> int:
    assert response.status_code == 429, response.text
    (item,) = response.json()["detail"]
    assert item["loc"] == ["body", "participant"] and item["type"] == "quota"
    assert setting in item["msg"]
    retry = int(response.headers["retry-after"])
    assert retry >= 1
    return retry


def test_versions_per_minute_and_refusals_do_not_use_the_quota(tmp_path) -> None:
    with quota_app(tmp_path, quota_versions_per_minute=2, refusal_cooldown_s=0.0) as client:
        name = unique("busy")
        first = client.post("/submit", json=honest(name)).json()
        token = first["token"]
        refused = client.post("/submit", json=saboteur(name), headers=bearer(token))
        assert refused.status_code == 201 and refused.json()["accepted"] is False
        assert client.post("/submit", json=honest(name), headers=bearer(token)).status_code == 201
        before = count(client, ModelVersion)
        third = client.post("/submit", json=honest(name), headers=bearer(token))
        retry = assert_throttled(third, "SRD_QUOTA_VERSIONS_PER_MINUTE")
        assert retry <= 60
        assert count(client, ModelVersion) == before
        other = unique("other")
        assert client.post("/submit", json=honest(other)).status_code == 201  # per participant


def test_refusals_in_a_row_cool_the_participant_down(tmp_path) -> None:
    with quota_app(tmp_path, refusal_cooldown_s=30.0) as client:
        name = unique("prober")
        token = client.post("/submit", json=honest(name)).json()["token"]
        refused = client.post("/submit", json=saboteur(name), headers=bearer(token))
        assert refused.json()["accepted"] is False
        before = count(client, ModelVersion)
        again = client.post("/submit", json=saboteur(name), headers=bearer(token))
        retry = assert_throttled(again, "SRD_REFUSAL_COOLDOWN_S")
        assert 25 <= retry <= 30
        assert "refused or held by the screener 1 time(s) in a row" in again.text
        assert "reasons" not in again.text  # the verdict of a throttled probe is not revealed
        assert count(client, ModelVersion) == before
        honest_too = client.post("/submit", json=honest(name), headers=bearer(token))
        assert_throttled(honest_too, "SRD_REFUSAL_COOLDOWN_S")  # whatever it sends


def _refused_probe(upload: Any) -> bytes:
    """``upload`` changed to buy more as the price rises: the screener refuses it."""
    probe = upload.model_dump(mode="json")
    probe["decision"]["B"]["weights"]["PG"] = 0.9
    return json.dumps(probe).encode()


def test_a_refused_round_upload_counts_as_a_refusal(tmp_path) -> None:
    """A round upload the screener refuses starts its participant's cooldown and spends its
    address's refusals per hour, as a refused /submit does: a round cannot be used to probe
    the screener past those limits."""
    with quota_app(tmp_path, refusal_cooldown_s=30.0, quota_address_refusals_per_hour=1) as client:
        remote = remote_auction(client, "round-prober", 900, seed=5)
        auction_id, model_id, token, upload = first_asked_upload(remote)
        answer = put(client, auction_id, 1, model_id, _refused_probe(upload), token)
        assert answer.status_code == 200 and answer.json()["accepted"] is False, answer.text
        again = client.post("/submit", json=honest(upload.participant), headers=bearer(token))
        assert_throttled(again, "SRD_QUOTA_ADDRESS_REFUSALS_PER_HOUR")  # the address's first
    with quota_app(tmp_path, refusal_cooldown_s=30.0) as same_database:  # its own limit off
        later = same_database.post(
            "/submit", json=honest(upload.participant), headers=bearer(token)
        )
        assert_throttled(later, "SRD_REFUSAL_COOLDOWN_S")
        assert "refused or held by the screener 1 time(s) in a row" in later.text


@contextlib.contextmanager
def screener_frozen() -> Iterator[None]:
    """This process's screening process stopped (SIGSTOP) while the block runs."""
    mine = [p for p in descendants(os.getpid()) if process_name(p) == "srd-screening"]
    assert mine, "no screening process"
    for pid in mine:
        os.kill(pid, signal.SIGSTOP)
    try:
        yield
    finally:
        for pid in mine:
            os.kill(pid, signal.SIGCONT)


def test_a_round_upload_sent_twice_at_once_counts_one_refusal(tmp_path) -> None:
    """The same refused upload sent again while the first waits for its verdict (an agent's
    retry after a timeout, to this replica or another): both hear the one verdict, and the
    participant's cooldown counts one refusal, not two (30 s, not 60)."""
    with quota_app(tmp_path, refusal_cooldown_s=30.0) as client:
        remote = remote_auction(client, "twice-prober", 940, seed=5)
        auction_id, model_id, token, upload = first_asked_upload(remote)
        body = _refused_probe(upload)
        pool = ThreadPoolExecutor(2)
        with screener_frozen():
            sent = [pool.submit(put, client, auction_id, 1, model_id, body, token) for _ in "ab"]
            time.sleep(1.0)  # both stored or waiting for the one stored
        answers = [future.result(timeout=120) for future in sent]
        pool.shutdown()
        assert [a.status_code for a in answers] == [200, 200], [a.text for a in answers]
        assert answers[0].json() == answers[1].json() and answers[0].json()["accepted"] is False
        again = client.post("/submit", json=honest(upload.participant), headers=bearer(token))
        assert 25 <= assert_throttled(again, "SRD_REFUSAL_COOLDOWN_S") <= 30
        assert "refused or held by the screener 1 time(s) in a row" in again.text


def test_a_round_upload_the_step_judged_counts_as_a_refusal(tmp_path) -> None:
    """The screener hangs past the round's deadline, so the step closing the round judges the
    waiting upload itself: its refusal starts the participant's cooldown as the API's verdict
    would have."""
    with quota_app(tmp_path, refusal_cooldown_s=30.0) as client:
        auction_id, manifests, patrons = start_remote(
            client, "step-prober", 960, 3, round_deadline_s=4, seed=5
        )
        state = open_round(client, auction_id)
        remote = {"id": auction_id, "manifests": manifests, "patrons": patrons, "state": state}
        auction_id, model_id, token, upload = first_asked_upload(remote)
        with screener_frozen():
            answer = put(client, auction_id, 1, model_id, _refused_probe(upload), token)
        assert answer.status_code == 200 and answer.json()["accepted"] is False, answer.text
        again = client.post("/submit", json=honest(upload.participant), headers=bearer(token))
        assert_throttled(again, "SRD_REFUSAL_COOLDOWN_S")
        assert "refused or held by the screener 1 time(s) in a row" in again.text


def test_an_accepted_round_upload_ends_the_refusals_in_a_row(tmp_path) -> None:
    """As an accepted version does: a patron refused once, then accepted in a round, is not
    cooled down at its next /submit."""
    with quota_app(tmp_path, refusal_cooldown_s=30.0) as client:
        remote = remote_auction(client, "round-mender", 920, seed=5)
        auction_id, model_id, token, upload = first_asked_upload(remote)
        name = upload.participant
        probe = client.post("/submit", json=saboteur(name), headers=bearer(token))
        assert probe.json()["accepted"] is False
        cooled = client.post("/submit", json=honest(name), headers=bearer(token))
        assert_throttled(cooled, "SRD_REFUSAL_COOLDOWN_S")
        answer = put(client, auction_id, 1, model_id, upload.model_dump_json().encode(), token)
        assert answer.status_code == 200 and answer.json()["accepted"] is True, answer.text
        again = client.post("/submit", json=honest(name), headers=bearer(token))
        assert again.status_code == 201, again.text


def test_registrations_per_address(tmp_path) -> None:
    with quota_app(tmp_path, quota_registrations_per_day=2) as client:
        assert client.post("/submit", json=honest(unique("one"))).status_code == 201
        assert client.post("/submit", json=honest(unique("two"))).status_code == 201
        before = count(client, Participant)
        third = client.post("/submit", json=honest(unique("three")))
        assert_throttled(third, "SRD_QUOTA_REGISTRATIONS_PER_DAY")
        assert count(client, Participant) == before


def test_an_ipv6_client_is_its_64_network(tmp_path) -> None:
    """One host usually holds a whole /64: its addresses share one quota (and one share of
    every per-address limit); another /64 is another client."""
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    settings = make_settings(url, tmp_path / "data").model_copy(
        update={"quota_registrations_per_day": 2}
    )
    app = create_app(settings)
    with TestClient(app, client=("2001:db8:0:7::1", 5000)) as first:
        assert first.post("/submit", json=honest(unique("v6-a"))).status_code == 201
        assert first.post("/submit", json=honest(unique("v6-b"))).status_code == 201
    with TestClient(app, client=("2001:db8:0:7:ffff::2", 5000)) as same_network:
        third = same_network.post("/submit", json=honest(unique("v6-c")))
        assert_throttled(third, "SRD_QUOTA_REGISTRATIONS_PER_DAY")
    with TestClient(app, client=("2001:db8:0:8::1", 5000)) as next_network:
        assert next_network.post("/submit", json=honest(unique("v6-d"))).status_code == 201


@pytest.mark.postgres
def test_limits_are_shared_by_processes_on_one_database(tmp_path) -> None:
    """Two API processes (replicas) on one PostgreSQL database count the same quotas."""
    admin_url = postgres_admin_url()
    if admin_url is None:
        pytest.skip("PostgreSQL is not reachable on 127.0.0.1:5432")
    limits: dict[str, Any] = {"quota_versions_per_minute": 1, "refusal_cooldown_s": 0.0}
    with (
        throwaway_postgres(admin_url) as url,
        quota_app(tmp_path / "a", url, **limits) as first,
        quota_app(tmp_path / "b", url, **limits) as second,
    ):
        name = unique("shared")
        token = first.post("/submit", json=honest(name)).json()["token"]
        elsewhere = second.post("/submit", json=honest(name), headers=bearer(token))
        assert_throttled(elsewhere, "SRD_QUOTA_VERSIONS_PER_MINUTE")
        assert count(first, RateEvent) >= 1


def test_unauthenticated_and_throttled_requests_cost_no_screening(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with quota_app(tmp_path, quota_versions_per_minute=1) as client:
        name = unique("cheap")
        token = client.post("/submit", json=honest(name)).json()["token"]
        screened: list[str] = []
        screening = client.app.state.services.screening  # type: ignore[attr-defined]
        real = screening.verdict

        async def counting(manifest: Any) -> Any:
            screened.append(manifest.participant)
            return await real(manifest)

        monkeypatch.setattr(screening, "verdict", counting)
        assert client.post("/submit", json=honest(name)).status_code == 401
        assert client.post("/submit", json=honest(name), headers=bearer("wrong")).status_code == 403
        over = client.post("/submit", json=honest(name), headers=bearer(token))
        assert_throttled(over, "SRD_QUOTA_VERSIONS_PER_MINUTE")
        assert screened == []


@pytest.mark.postgres
def test_concurrent_submissions_from_one_address_keep_its_quota(tmp_path) -> None:
    """Submissions racing each other from one address each count the others' events: no more
    registrations are stored than the address's quota, however many arrive at once."""
    admin_url = postgres_admin_url()
    if admin_url is None:
        pytest.skip("PostgreSQL is not reachable on 127.0.0.1:5432")
    with (
        throwaway_postgres(admin_url) as url,
        quota_app(tmp_path, url, quota_registrations_per_day=3) as client,
    ):
        start = threading.Barrier(12)

        def register(i: int) -> int:
            start.wait()
            return client.post("/submit", json=honest(unique(f"racer{i}"))).status_code

        with ThreadPoolExecutor(12) as pool:
            statuses = list(pool.map(register, range(12)))
        assert sorted(statuses) == [201] * 3 + [429] * 9, statuses
        assert count(client, Participant) == 3
