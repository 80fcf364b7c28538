"""Cancelling an auction (``DELETE /auctions/{id}``, operator): a pending one, a running one whose
worker keeps playing (it commits nothing more), a remote one with an open round while an agent
long-polls it and another waits on its round socket (both answered at once, the round closed,
a later upload 410), and ``srd agents`` on a live server stopping cleanly for it; every
refusal (401, 403, 404, 409, 422) changes nothing."""

from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from agents.manifest import parse_manifest
from agents.negotiator import honest_manifest
from agents.remote import RoundInfo, faithful_fine_tune
from server.cli.launch import ServerProcess
from server.config import Settings
from tests.server.test_remote_protocol import put, remote_auction
from tests.support.factories import honest, unique
from tests.support.live import create_unstarted_auction, data, paced_auction, sse_events
from tests.support.remote import agents_process, honest_remote_auction, next_round
from tests.support.server import ADMIN, wait_for

WAKE_S = 2.0
"""How soon after the cancel a waiting agent must have its answer."""


def cancel(client: TestClient, auction_id: int | str, **headers: str) -> Any:
    return client.delete(f"/auctions/{auction_id}", headers=headers or ADMIN)


def error(response: Any, status: int, loc: list[Any], words: str) -> None:
    assert response.status_code == status, response.text
    (item,) = response.json()["detail"]
    assert item["loc"] == loc and words in item["msg"], response.text


def events(client: TestClient, auction_id: int) -> list[dict[str, str]]:
    """Every event of the auction's stream until the server ends it (comments left out)."""
    with client.stream("GET", f"/auctions/{auction_id}/events") as response:
        return [e for e in sse_events(response) if "event" in e]


@pytest.fixture(scope="module")
def patrons(client: TestClient) -> list[int]:
    """Five honest models (seed 1 is held for review)."""
    ids = []
    for seed in (0, 2, 3, 4, 5):
        answer = client.post("/submit", json=honest(unique("cancel"), seed=seed))
        assert answer.status_code == 201, answer.text
        ids.append(answer.json()["model_id"])
    return ids


def test_the_openapi_document_lists_the_cancel(client: TestClient) -> None:
    operation = client.get("/openapi.json").json()["paths"]["/auctions/{auction_id}"]["delete"]
    assert operation["operationId"] == "cancel_auction"
    assert {} not in operation["security"]  # the operator's token is required
    assert {"200", "401", "403", "404", "409", "422"} <= set(operation["responses"])
    schema = operation["responses"]["200"]["content"]["application/json"]["schema"]
    assert schema == {"$ref": "#/components/schemas/AuctionPublic"}


def test_a_pending_auction_is_cancelled_and_its_stream_ends_with_it(
    client: TestClient, settings: Settings, patrons: list[int], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO)
    # Leased to the tests: no worker ever starts it.
    auction_id = create_unstarted_auction(settings.database_url, patrons, n_fish=2, seed=1)
    assert client.get(f"/auctions/{auction_id}").json()["status"] == "pending"
    name = client.get(f"/models/{patrons[0]}").json()["participant"]

    def outcome() -> str:  # the patron's, on its participant's page
        entries = client.get(f"/participants/{name}").json()["auctions"]
        return next(str(e["outcome"]) for e in entries if e["auction_id"] == auction_id)

    assert outcome() == "joined"
    answer = cancel(client, auction_id)
    assert answer.status_code == 200, answer.text
    state = answer.json()
    assert state["status"] == "cancelled" and state["stop_reason"] == "cancelled"
    assert state["error"] is None and state["started_at"] is None
    assert state["finished_at"] is not None and state["history"] == []
    assert state["iteration"] == 0 and state["n_available"] == 2 and state["buyers"] == []
    assert outcome() == "stopped"
    assert f"auction {auction_id} cancelled" in caplog.messages
    assert client.get(f"/auctions/{auction_id}").json() == state
    listed = client.get("/auctions").json()["items"]
    assert next(a for a in listed if a["id"] == auction_id)["status"] == "cancelled"
    (end,) = events(client, auction_id)
    assert end["event"] == "end"
    assert data(end)["status"] == "cancelled" and data(end)["iterations"] == 0
    assert data(end)["stop_reason"] == "cancelled"
    again = cancel(client, auction_id)
    error(again, 409, ["path", "auction_id"], f"auction {auction_id} already cancelled")
    assert client.get(f"/auctions/{auction_id}").json() == state


def test_refusals_change_nothing(
    client: TestClient, settings: Settings, patrons: list[int]
) -> None:
    auction_id = create_unstarted_auction(settings.database_url, patrons, n_fish=1, seed=2)
    before = client.get(f"/auctions/{auction_id}").json()
    missing = client.delete(f"/auctions/{auction_id}")
    error(missing, 401, ["header", "Authorization"], "operator endpoint")
    wrong = cancel(client, auction_id, Authorization="Bearer not-the-admin-token")
    error(wrong, 403, ["header", "Authorization"], "not the admin token")
    error(cancel(client, 987654), 404, ["path", "auction_id"], "auction 987654 does not exist")
    assert cancel(client, "1.0").status_code == 422
    assert cancel(client, 0).status_code == 422
    assert client.get(f"/auctions/{auction_id}").json() == before
    assert before["status"] == "pending"


def test_a_finished_auction_cannot_be_cancelled(client: TestClient, patrons: list[int]) -> None:
    created = client.post("/auctions", json={"n_fish": 1, "model_ids": patrons}, headers=ADMIN)
    auction_id = created.json()["auction_id"]
    done = wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] not in ("pending", "running"),
        60,
    )
    assert done["status"] == "finished", done
    error(cancel(client, auction_id), 409, ["path", "auction_id"], "already finished")
    assert client.get(f"/auctions/{auction_id}").json() == done


def test_a_running_auction_keeps_its_rounds_and_its_worker_commits_nothing_more(
    client: TestClient,
    settings: Settings,
    patrons: list[int],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The auction is played by the server's own worker code in a thread of the test, which the
    cancel cannot stop: it plays on and tries to commit its next round, and gains nothing."""
    auction_id = create_unstarted_auction(settings.database_url, patrons, n_fish=1, seed=1)
    followed: list[dict[str, str]] = []
    with paced_auction(
        monkeypatch, settings.database_url, settings.data_dir, auction_id, pace_s=0.4
    ) as worker:
        wait_for(
            lambda: client.get(f"/auctions/{auction_id}").json(),
            lambda a: len(a["history"]) >= 1,
            60,
        )
        stream = threading.Thread(target=lambda: followed.extend(events(client, auction_id)))
        stream.start()
        answer = cancel(client, auction_id)
        cancelled_at = time.monotonic()
        assert answer.status_code == 200, answer.text
        state = answer.json()
        assert state["status"] == "cancelled" and state["stop_reason"] == "cancelled"
        assert state["started_at"] is not None and state["error"] is None
        assert len(state["history"]) == state["iteration"] >= 1
        # The worker's next commit is refused (the auction is no longer running): it stops.
        worker.join(10)
        assert not worker.is_alive()
        stream.join(10)
        assert not stream.is_alive() and time.monotonic() - cancelled_at < 10
    after = client.get(f"/auctions/{auction_id}").json()
    assert after == state
    iterations = [e for e in followed if e["event"] == "iteration"]
    assert [int(e["id"]) for e in iterations] == list(range(len(state["history"])))
    assert followed[-1]["event"] == "end" and data(followed[-1])["status"] == "cancelled"
    assert data(followed[-1])["iterations"] == len(state["history"])


def test_a_remote_auction_closes_its_round_and_wakes_its_agents(client: TestClient) -> None:
    remote = remote_auction(client, "cancel-remote", 308, seed=5)
    auction_id, round_state = remote["id"], remote["state"]
    asked = [(p, m, t) for p, (m, t) in enumerate(remote["patrons"]) if m in round_state["asked"]]
    (first, first_id, first_token), (late, late_id, late_token) = asked[0], asked[1]

    def tuned(position: int) -> bytes:
        manifest = parse_manifest(remote["manifests"][position])
        info = RoundInfo.from_state(round_state, position)
        return faithful_fine_tune(manifest, info).model_dump_json().encode()

    answered = put(client, auction_id, 1, first_id, tuned(first), first_token)
    assert answered.status_code == 200, answered.text
    runner = client.app.state.services.auctions  # type: ignore[attr-defined]
    # An open round holds no worker: the step that opened it has ended.
    wait_for(lambda: {"held": auction_id in runner.held}, lambda s: not s["held"], 10)

    polled: dict[str, Any] = {}

    def long_poll() -> None:
        response = client.get(
            f"/auctions/{auction_id}/rounds/current", params={"wait": 25, "after": 1}
        )
        polled.update(at=time.monotonic(), status=response.status_code, body=response.json())

    pushed: list[tuple[float, dict[str, Any]]] = []
    connected = threading.Event()

    def socket() -> None:
        with client.websocket_connect(f"/auctions/{auction_id}/rounds/socket") as ws:
            for _ in range(2):  # the open round on connecting, then the cancel
                frame = json.loads(ws.receive_text())
                pushed.append((time.monotonic(), frame))
                connected.set()

    waiters = [threading.Thread(target=long_poll), threading.Thread(target=socket)]
    for waiter in waiters:
        waiter.start()
    assert connected.wait(10)
    time.sleep(0.5)  # the long poll waits by now
    assert not polled
    cancelled_at = time.monotonic()  # the DELETE's request goes out
    answer = cancel(client, auction_id)
    assert answer.status_code == 200, answer.text
    for waiter in waiters:
        waiter.join(WAKE_S + 5)
        assert not waiter.is_alive()
    assert polled["status"] == 200 and polled["at"] - cancelled_at < WAKE_S
    assert polled["body"]["auction_status"] == "cancelled"
    assert polled["body"]["status"] == "closed" and polled["body"]["round"] == 1
    assert pushed[0][1]["body"]["status"] == "open"
    at, frame = pushed[1]
    assert at - cancelled_at < WAKE_S and frame["type"] == "round"
    assert frame["body"]["auction_status"] == "cancelled" and frame["body"]["status"] == "closed"

    state = answer.json()
    assert state["status"] == "cancelled" and state["stop_reason"] == "cancelled"
    assert len(state["history"]) == 1  # iteration 0, which opened round 1
    (closed,) = state["fine_tuning"]
    assert closed["status"] == "closed" and closed["closed_at"] == state["finished_at"]
    assert {a["model_id"]: a["outcome"] for a in closed["answers"]} == {first_id: "accepted"}
    # No step runs for it again, not even at the round's deadline.
    assert auction_id not in runner.held and runner.pool.pid(auction_id) is None
    # A later upload hears that the round is closed, and is recorded late.
    refused = put(client, auction_id, 1, late_id, tuned(late), late_token)
    error(refused, 410, ["path", "round"], "round 1 is closed: the auction was cancelled")
    after = client.get(f"/auctions/{auction_id}").json()
    outcomes = {a["model_id"]: a["outcome"] for a in after["fine_tuning"][0]["answers"]}
    assert outcomes == {first_id: "accepted", late_id: "late"}
    assert after["history"] == state["history"] and after["status"] == "cancelled"
    # The accepted version is stored, but the auction, cancelled, never bid with it.
    assert after["current_model_ids"] == after["model_ids"]


@pytest.fixture
def live_server(tmp_path: Path) -> Iterator[ServerProcess]:
    token = secrets.token_hex(16)
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    with ServerProcess(database_url=url, data_dir=tmp_path, admin_token=token) as server:
        yield server


@pytest.mark.slow  # the default run keeps its neighbours (docs/development.md)
def test_srd_agents_stops_cleanly_for_a_cancelled_auction(live_server: ServerProcess) -> None:
    """The agents answer round 1; a patron that never answers keeps it open; the operator
    cancels: ``srd agents`` ends at once with exit 0 and reports the cancelled auction."""
    admin = {"Authorization": f"Bearer {live_server.admin_token}"}
    with httpx.Client(base_url=live_server.url, timeout=30) as http:
        silent = honest_manifest(np.random.default_rng(100), unique("silent"))
        submitted = http.post("/submit", content=silent.model_dump_json(), headers=JSON)
        silent_id = submitted.raise_for_status().json()["model_id"]
        prefix = unique("agents")
        agents = agents_process(live_server, prefix, "--honest", "2", "--seed", "3")
        try:
            names = [f"{prefix}-honest-{i:03d}" for i in range(2)]
            ids = [_model_of(http, name) for name in names]
            body = {
                "n_fish": 1,
                "model_ids": [*ids, silent_id],
                "fine_tune_mode": "remote",
                "fine_tune_rounds": 2,
                "round_deadline_s": 120,
            }
            created = http.post("/auctions", json=body, headers=admin).raise_for_status()
            auction_id = created.json()["auction_id"]
            round_state = next_round(live_server, auction_id, 0, 120)
            assert round_state["status"] == "open" and silent_id in round_state["asked"]
            asked_agents = [m for m in round_state["asked"] if m != silent_id]
            assert asked_agents, round_state  # the agents have a round to answer
            wait_for(
                lambda: http.get(f"/auctions/{auction_id}").json()["fine_tuning"][0],
                lambda r: len(r["answers"]) == len(asked_agents),
                60,
            )
            assert http.delete(f"/auctions/{auction_id}", headers=admin).status_code == 200
            out, err = agents.communicate(timeout=30)
        finally:
            if agents.poll() is None:
                agents.kill()
                agents.wait()
    assert agents.returncode == 0, err
    report = json.loads(out)
    assert report["auctions"] == [auction_id] and report["rounds"] == 1
    assert report["auction"]["status"] == "cancelled"
    assert report["auction"]["stop_reason"] == "cancelled"
    uploads = report["uploads"]
    assert uploads["accepted"] + uploads["refused"] == len(asked_agents) and uploads["late"] == 0


@pytest.mark.parametrize(
    "transport",
    ["websocket", pytest.param("http", marks=pytest.mark.slow)],  # 12 s each
)
def test_an_upload_sent_as_the_auction_is_cancelled_is_answered(
    live_server: ServerProcess, transport: str
) -> None:
    """The agent fine-tunes while the operator cancels: its upload, sent after the cancel,
    still gets its answer (410, late), on the socket or by its PUT, and the agent stops at
    once instead of retrying until it gives up."""
    import asyncio

    from agents.remote import Client, RemoteAgent

    admin = {"Authorization": f"Bearer {live_server.admin_token}"}
    auction_id, entered = honest_remote_auction(
        live_server, (0, 2, 3), name="racer", n_fish=1, round_deadline_s=60
    )
    with httpx.Client(base_url=live_server.url, timeout=30) as http:

        def cancel_then_tune(current: Any, info: RoundInfo) -> Any:
            assert http.delete(f"/auctions/{auction_id}", headers=admin).status_code == 200
            time.sleep(0.5)
            return faithful_fine_tune(current, info)

        model_id, token, manifest = entered[0]

        async def play() -> RemoteAgent:
            async with httpx.AsyncClient(base_url=live_server.url) as client:
                agent = RemoteAgent(
                    Client(client, give_up_s=20),
                    parse_manifest(manifest),
                    fine_tuner=cancel_then_tune,
                    token=token,
                    model_id=model_id,
                    transport=transport,  # type: ignore[arg-type]
                )
                await agent.play(auction_id)
                return agent

        started = time.monotonic()
        agent = asyncio.run(play())
        took = time.monotonic() - started
    assert took < 10, took
    assert agent.uploads.late == 1 and [entry.outcome for entry in agent.log] == ["late"]


JSON = {"Content-Type": "application/json"}


def _model_of(http: httpx.Client, participant: str) -> int:
    """The model id of a participant once it has submitted (the agents register first)."""
    page = wait_for(
        lambda: http.get("/models", params={"participant": participant}).json(),
        lambda p: bool(p["items"]),
        120,
    )
    return int(page["items"][0]["id"])
