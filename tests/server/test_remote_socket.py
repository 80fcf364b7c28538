"""The round socket in-process (``WS /auctions/{id}/rounds/socket``): rounds pushed as the long
poll shows them, uploads answered exactly as a PUT answers them (the same stored outcome for
the same bytes on either transport), every refusal naming its field with nothing stored, and
the socket's own limits: unknown auctions, too many sockets, too many messages."""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from contextlib import ExitStack
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.pool import NullPool
from starlette.testclient import WebSocketDenialResponse
from starlette.websockets import WebSocketDisconnect

import server.auctions.sockets as sockets_module
from agents.manifest import parse_manifest
from agents.remote import RoundInfo, faithful_fine_tune
from server.auctions.sockets import BURST, MAX_FRAME_BYTES, UPLOAD_MAX_BYTES
from server.config import Settings
from server.store.db import is_sqlite, sqlite_path
from tests.server.test_remote_protocol import (
    bearer,
    loc_of,
    put,
    remote_auction,
    stored_versions,
)
from tests.support.server import ADMIN

SEED = 900
"""Patrons seeds 900..907 (any honest draws: the tests below use the asked ones)."""


@pytest.fixture(scope="module")
def remote(client: TestClient) -> dict[str, Any]:
    """A remote auction of 8 fine-tuning honest patrons, round 1 open for a minute; ``asked``:
    the positions asked in it."""
    remote = remote_auction(client, "socket", SEED, seed=9)
    patrons, asked_ids = remote["patrons"], remote["state"]["asked"]
    asked = [p for p, (m, _) in enumerate(patrons) if m in asked_ids]
    assert len(asked) >= 3, asked_ids
    return {**remote, "asked": asked}


@pytest.fixture(scope="module")
def busy(client: TestClient) -> dict[str, Any]:
    """Another such auction, for the tests that hold uploads in flight."""
    remote = remote_auction(client, "busy", SEED + 20, seed=11)
    patrons, asked_ids = remote["patrons"], remote["state"]["asked"]
    asked = [p for p, (m, _) in enumerate(patrons) if m in asked_ids]
    assert len(asked) >= 2, asked_ids
    return {**remote, "asked": asked}


def socket_path(auction_id: int) -> str:
    return f"/auctions/{auction_id}/rounds/socket"


def upload_text(round_: int, model_id: int, manifest: str) -> str:
    return json.dumps(
        {"type": "upload", "round": round_, "model_id": model_id, "manifest": manifest}
    )


def answer_to(ws: Any, text: str) -> dict[str, Any]:
    """Send one message; the answer frame (rounds pushed meanwhile are skipped)."""
    ws.send_text(text)
    while True:
        frame = json.loads(ws.receive_text())
        if frame["type"] == "answer":
            return dict(frame)


def answer_of(ws: Any) -> dict[str, Any]:
    """The next answer frame (rounds pushed meanwhile are skipped)."""
    while True:
        frame = json.loads(ws.receive_text())
        if frame["type"] == "answer":
            return dict(frame)


def tuned_bytes(remote: dict[str, Any], position: int) -> bytes:
    manifest = parse_manifest(remote["manifests"][position])
    tuned = faithful_fine_tune(manifest, RoundInfo.from_state(remote["state"], position))
    return tuned.model_dump_json().encode()


def without_clock(state: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in state.items() if k != "seconds_left"}


def test_the_socket_pushes_the_round_the_long_poll_shows(
    client: TestClient, remote: dict[str, Any]
) -> None:
    with client.websocket_connect(socket_path(remote["id"])) as ws:
        frame = json.loads(ws.receive_text())
    assert frame["type"] == "round"
    polled = client.get(f"/auctions/{remote['id']}/rounds/current").json()
    assert without_clock(frame["body"]) == without_clock(polled)
    assert frame["body"]["round"] == 1 and frame["body"]["status"] == "open"
    assert len(frame["body"]["rows"]) == 64 and frame["body"]["asked"]


def test_a_socket_upload_is_answered_and_stored_as_a_put_would(
    client: TestClient, remote: dict[str, Any]
) -> None:
    position = remote["asked"][0]
    model_id, token = remote["patrons"][position]
    name = parse_manifest(remote["manifests"][position]).participant
    good = tuned_bytes(remote, position)
    with client.websocket_connect(socket_path(remote["id"]), headers=bearer(token)) as ws:
        json.loads(ws.receive_text())  # the round
        first = answer_to(ws, upload_text(1, model_id, good.decode()))
        assert (first["round"], first["model_id"], first["status"]) == (1, model_id, 200), first
        answer = first["body"]
        assert answer["accepted"] and answer["outcome"] == "accepted" and answer["version"] == 2
        again = answer_to(ws, upload_text(1, model_id, good.decode()))
        assert again == first
    # The same bytes by PUT: the same answer; other bytes: 409 on either transport.
    put_again = put(client, remote["id"], 1, model_id, good, token)
    assert put_again.status_code == 200 and put_again.json() == answer
    with client.websocket_connect(socket_path(remote["id"]), headers=bearer(token)) as ws:
        other = answer_to(ws, upload_text(1, model_id, good.decode() + " "))
    assert other["status"] == 409 and "one upload per round" in json.dumps(other)
    assert other["body"]["detail"][0]["loc"] == ["message", "round"]
    assert stored_versions(client, name) == 2
    version = client.get(f"/models/{answer['model_id']}").json()
    assert version["parent_id"] == model_id and version["round"] == 1
    assert parse_manifest(version["manifest"]).model_dump_json().encode() == good


def refusal(frame: dict[str, Any], status: int, loc: list[Any], words: str) -> None:
    assert frame["type"] == "answer" and frame["status"] == status, frame
    assert loc in [item["loc"] for item in frame["body"]["detail"]], frame
    assert words in json.dumps(frame), frame


def test_socket_refusals_name_the_field_and_store_nothing(
    client: TestClient, remote: dict[str, Any]
) -> None:
    position = remote["asked"][1]
    model_id, token = remote["patrons"][position]
    name = parse_manifest(remote["manifests"][position]).participant
    _, other_token = remote["patrons"][remote["asked"][2]]
    good = tuned_bytes(remote, position).decode()
    path = socket_path(remote["id"])
    with client.websocket_connect(path) as ws:  # no token in the handshake
        refusal(
            answer_to(ws, upload_text(1, model_id, good)), 401, ["header", "Authorization"], "token"
        )
    with client.websocket_connect(path, headers=bearer(other_token)) as ws:
        refusal(
            answer_to(ws, upload_text(1, model_id, good)), 403, ["header", "Authorization"], name
        )
    with client.websocket_connect(path, headers=bearer(token)) as ws:
        refusal(answer_to(ws, "not json"), 422, ["message"], "not JSON")
        refusal(answer_to(ws, "[" * 40 + "]" * 40), 422, ["message"], "nested deeper")
        refusal(answer_to(ws, "[" * 60_000 + "]" * 60_000), 422, ["message"], "arrays and objects")
        ws.send_bytes(b"{}")
        refusal(json.loads(ws.receive_text()), 422, ["message"], "text frames")
        extra = json.dumps(
            {"type": "upload", "round": 1, "model_id": model_id, "manifest": good, "x": 1}
        )
        refusal(answer_to(ws, extra), 422, ["message", "x"], "Extra")
        twice = upload_text(1, model_id, good).replace('"round": 1', '"round": 1, "round": 2', 1)
        assert '"round": 2' in twice
        refusal(answer_to(ws, twice), 422, ["message", "round"], "appears twice")
        refusal(answer_to(ws, upload_text(0, model_id, good)), 422, ["message", "round"], "greater")
        refusal(
            answer_to(ws, upload_text(2, model_id, good)),
            409,
            ["message", "round"],
            "the current round is 1 (open)",
        )
        refusal(answer_to(ws, upload_text(1, 987654, good)), 404, ["message", "model_id"], "987654")
        huge = answer_to(ws, upload_text(1, 10**4000, good))  # 4,001 digits: not echoed back
        refusal(huge, 422, ["message", "model_id"], "less than or equal")
        assert huge["model_id"] is None and len(json.dumps(huge)) < 2_000, huge
        # The body checks' refusals, in the message's terms
        refusal(
            answer_to(ws, upload_text(1, model_id, "{nope")),
            422,
            ["message", "manifest"],
            "the manifest is not JSON",
        )
        many = "[" + ",".join(["{}"] * 2_100) + "]"
        refusal(
            answer_to(ws, upload_text(1, model_id, many)),
            422,
            ["message", "manifest"],
            "in one manifest",
        )
        for whole in ("[1, 2]", '"x"', "3"):  # not an object: the manifest as a whole
            not_object = answer_to(ws, upload_text(1, model_id, whole))
            refusal(not_object, 422, ["message", "manifest"], "valid dictionary")
            assert len(not_object["body"]["detail"]) == 1, not_object
        padded = good[:-1] + " " * UPLOAD_MAX_BYTES + "}"
        refusal(
            answer_to(ws, upload_text(1, model_id, padded)),
            413,
            ["message", "manifest"],
            str(UPLOAD_MAX_BYTES),
        )
        nan = good.replace('"bias":', '"bias":NaN,"was":', 1)
        refusal(
            answer_to(ws, upload_text(1, model_id, nan)),
            422,
            ["message", "manifest", "external_sensor", "PG", "bias"],
            "finite",
        )
        data = json.loads(good)
        del data["decision"]["B"]["bias"]
        refusal(
            answer_to(ws, upload_text(1, model_id, json.dumps(data))),
            422,
            ["message", "manifest", "decision", "B", "bias"],
            "",
        )
        data = json.loads(good)
        data["augmentation"]["copies"] = 3
        refusal(
            answer_to(ws, upload_text(1, model_id, json.dumps(data))),
            422,
            ["message", "manifest", "augmentation", "copies"],
            "only weights and biases",
        )
    # An auction without remote rounds: the fault is the socket's path, not the message. It
    # stays pending (enrolling) meanwhile: an auction that has ended closes its sockets at once.
    plain = client.post(
        "/auctions", json={"n_fish": 1, "model_ids": [model_id], "enrollment_s": 120}, headers=ADMIN
    )
    with client.websocket_connect(
        socket_path(plain.json()["auction_id"]), headers=bearer(token)
    ) as ws:
        refusal(
            answer_to(ws, upload_text(1, model_id, good)), 409, ["path", "auction_id"], "no remote"
        )
    cancelled = client.delete(f"/auctions/{plain.json()['auction_id']}", headers=ADMIN)
    assert cancelled.status_code == 200, cancelled.text
    assert stored_versions(client, name) == 1
    auction = client.get(f"/auctions/{remote['id']}").json()
    answered = {a["model_id"] for r in auction["fine_tuning"] for a in r["answers"]}
    assert model_id not in answered


def test_handshakes_are_refused_for_a_bad_or_unknown_auction_and_beyond_the_limit(
    client: TestClient, remote: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    with (
        pytest.raises(WebSocketDenialResponse) as missing,
        client.websocket_connect(socket_path(987654)),
    ):
        pass
    assert missing.value.status_code == 404
    assert missing.value.json()["detail"][0]["loc"] == ["path", "auction_id"]
    for header in ("Basic eDp5", "Bearer", "Bearer   ", "srdp_no-scheme"):  # told at once
        with (
            pytest.raises(WebSocketDenialResponse) as malformed,
            client.websocket_connect(socket_path(remote["id"]), headers={"Authorization": header}),
        ):
            pass
        assert malformed.value.status_code == 401, header
        [item] = malformed.value.json()["detail"]
        assert item["loc"] == ["header", "Authorization"] and item["type"] == "bad_authorization"
    for foreign in ({"Origin": "https://evil.example"}, {"Sec-Fetch-Site": "cross-site"}):
        with (  # another site's page: it would take the visitor's address's share of sockets
            pytest.raises(WebSocketDenialResponse) as refused,
            client.websocket_connect(socket_path(remote["id"]), headers=foreign),
        ):
            pass
        assert refused.value.status_code == 403
        [item] = refused.value.json()["detail"]
        assert item["loc"] == ["header", next(iter(foreign))] and item["type"] == "cross_site"
    for bad in ("abc", "0", "99999999999"):
        with (
            pytest.raises(WebSocketDenialResponse) as invalid,
            client.websocket_connect(f"/auctions/{bad}/rounds/socket"),
        ):
            pass
        assert invalid.value.status_code == 422, bad
        assert invalid.value.json()["detail"][0]["loc"] == ["path", "auction_id"], bad
    # It takes no query parameter: one is refused naming it, as every HTTP route does.
    with (
        pytest.raises(WebSocketDenialResponse) as unknown,
        client.websocket_connect(socket_path(remote["id"]) + "?x=1"),
    ):
        pass
    assert unknown.value.status_code == 422
    (item,) = unknown.value.json()["detail"]
    assert item["loc"] == ["query", "x"] and item["type"] == "unknown_parameter"
    assert "'x' (this path takes: none)" in item["msg"]
    # Watchers (no token, or not the auction's) have a share apart from the patrons': with
    # theirs full, a patron still gets its socket.
    with client.websocket_connect(socket_path(remote["id"])) as watching:
        assert json.loads(watching.receive_text())["type"] == "round"
        monkeypatch.setattr(sockets_module, "MAX_WATCHER_SOCKETS", 1)
        with (
            pytest.raises(WebSocketDenialResponse) as full,
            client.websocket_connect(socket_path(remote["id"])),
        ):
            pass
        assert full.value.status_code == 503 and full.value.headers["Retry-After"] == "1"
        assert "watchers' (no patron's token) round sockets are open" in full.value.text
        (_, token) = remote["patrons"][0]
        with (
            client.websocket_connect(socket_path(remote["id"]), headers=bearer(token)) as ws,
            client.websocket_connect(socket_path(remote["id"]), headers=bearer(token)) as again,
        ):
            assert json.loads(ws.receive_text())["type"] == "round"
            assert json.loads(again.receive_text())["type"] == "round"
            # Its share of the patrons' sockets (2 per auction) taken: a third is refused,
            # saying so (not that the watchers' sockets are full: it sent a patron's token).
            with (
                pytest.raises(WebSocketDenialResponse) as third,
                client.websocket_connect(socket_path(remote["id"]), headers=bearer(token)),
            ):
                pass
            assert third.value.status_code == 503 and third.value.headers["Retry-After"] == "1"
            (item,) = third.value.json()["detail"]
            assert "this participant holds 2 of the patrons' round sockets" in item["msg"]
            assert "watchers'" not in item["msg"]
    with client.websocket_connect(socket_path(remote["id"])) as ws:  # released: room again
        assert json.loads(ws.receive_text())["type"] == "round"


def test_a_socket_over_its_message_allowance_is_closed(
    client: TestClient, remote: dict[str, Any]
) -> None:
    with client.websocket_connect(socket_path(remote["id"])) as ws:
        json.loads(ws.receive_text())
        for _ in range(2 * BURST):
            ws.send_text("x")
        statuses = []
        with pytest.raises(WebSocketDisconnect) as closed:
            while True:
                statuses.append(json.loads(ws.receive_text())["status"])
    assert closed.value.code == 1008 and "messages" in closed.value.reason
    assert BURST <= len(statuses) < 2 * BURST and set(statuses) == {422}


def test_a_frame_over_the_limit_closes_the_socket(
    client: TestClient, remote: dict[str, Any]
) -> None:
    # The limit is in bytes: a third as many three-byte characters reach it too.
    for text in (" " * (MAX_FRAME_BYTES + 1), "€" * (MAX_FRAME_BYTES // 3 + 1)):
        with client.websocket_connect(socket_path(remote["id"])) as ws:
            json.loads(ws.receive_text())
            ws.send_text(text)
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_text()
        assert closed.value.code == 1009 and str(MAX_FRAME_BYTES) in closed.value.reason


def test_a_socket_whose_rounds_cannot_be_read_is_closed_for_the_agent_to_reconnect(
    client: TestClient, remote: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    watcher = client.app.state.services.rounds  # type: ignore[attr-defined]
    calls = 0
    published = watcher.published

    async def failing(*args: Any, **kwargs: Any) -> Any:
        nonlocal calls
        calls += 1
        if calls > 1:  # the handshake's read works, the pusher's next one fails
            raise OSError("the database is unavailable")
        return await published(*args, **kwargs)

    monkeypatch.setattr(watcher, "published", failing)
    with client.websocket_connect(socket_path(remote["id"])) as ws:
        assert json.loads(ws.receive_text())["type"] == "round"
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_text()
    assert closed.value.code == 1011 and "reconnect" in closed.value.reason


def test_an_upload_whose_database_connection_is_cut_hears_503_and_counts_on_its_retry(
    client: TestClient, settings: Settings, busy: dict[str, Any]
) -> None:
    """The database connection under a socket upload is cut (PostgreSQL terminates it, as a
    restart or a failover does): the answer is the 503 a PUT would get, which an agent waits out
    and retries. It had been a 500, and ``srd agents`` had dropped such agents for the rest of
    the auction. The retry is accepted."""
    if is_sqlite(settings.database_url):
        pytest.skip("PostgreSQL cuts a connection under an upload")
    from sqlalchemy import create_engine, text

    position = busy["asked"][1]
    model_id, token = busy["patrons"][position]
    good = tuned_bytes(busy, position)
    holder = create_engine(settings.database_url, poolclass=NullPool)
    with client.websocket_connect(socket_path(busy["id"]), headers=bearer(token)) as ws:
        assert json.loads(ws.receive_text())["type"] == "round"
        with holder.connect() as locking:
            locking.execute(text("LOCK TABLE fine_tune_answers IN ACCESS EXCLUSIVE MODE"))
            ws.send_text(upload_text(1, model_id, good.decode()))
            waiting: list[int] = []
            deadline = time.monotonic() + 20
            while not waiting:  # the upload's write, waiting for the lock
                assert time.monotonic() < deadline, "the upload never waited for the lock"
                time.sleep(0.05)
                with holder.connect() as looking:
                    waiting = list(
                        looking.scalars(
                            text(
                                "SELECT pid FROM pg_stat_activity WHERE wait_event_type = 'Lock'"
                                " AND datname = current_database()"
                            )
                        )
                    )
            with holder.connect() as cutting:
                for pid in waiting:
                    cutting.execute(text("SELECT pg_terminate_backend(:pid)"), {"pid": pid})
            locking.rollback()
        frame = answer_of(ws)
    holder.dispose()
    assert frame["status"] == 503, frame
    (item,) = frame["body"]["detail"]
    assert item["type"] == "db_unavailable", item
    retried = put(client, busy["id"], 1, model_id, good, token)
    assert retried.status_code == 200 and retried.json()["outcome"] == "accepted", retried.text


def test_a_token_has_two_uploads_in_flight_at_most_over_sockets_too(
    client: TestClient, settings: Settings, busy: dict[str, Any]
) -> None:
    """A token's uploads in flight are bounded on its sockets as by PUT (2, shared between
    them): before, each socket of a token had one in flight, 128 in all. Here SQLite's write
    lock, held by another connection, holds two uploads in flight."""
    if not is_sqlite(settings.database_url):
        pytest.skip("SQLite's write lock holds the uploads in flight")
    position = busy["asked"][0]
    model_id, token = busy["patrons"][position]
    good = tuned_bytes(busy, position)
    text = upload_text(1, model_id, good.decode())
    path = socket_path(busy["id"])
    refused: list[Any] = []
    with ExitStack() as stack:
        sockets = [
            stack.enter_context(client.websocket_connect(path, headers=bearer(token)))
            for _ in range(3)
        ]
        for ws in sockets:
            assert json.loads(ws.receive_text())["type"] == "round"
        holder = sqlite3.connect(sqlite_path(settings.database_url), isolation_level=None)
        holder.execute("BEGIN IMMEDIATE")
        try:
            for ws in sockets[:2]:
                ws.send_text(text)
            time.sleep(2.0)  # both reach the server and wait for the lock

            def third() -> None:
                refused.append(answer_to(sockets[2], text))
                refused.append(put(client, busy["id"], 1, model_id, good, token))

            asker = threading.Thread(target=third, daemon=True)
            asker.start()
            asker.join(timeout=20)
            assert len(refused) == 2, "an upload past the token's share was not refused"
        finally:
            holder.execute("ROLLBACK")
            holder.close()
        answers = [answer_of(ws) for ws in sockets[:2]]
        again = answer_to(sockets[2], text)  # its turn now: the same answer
    frame, response = refused
    assert frame["status"] == 429 and (frame["round"], frame["model_id"]) == (1, model_id)
    (item,) = frame["body"]["detail"]
    assert item["loc"] == ["client"] and "holds 2 uploads already" in item["msg"], item
    assert response.status_code == 429 and loc_of(response) == [["client"]], response.text
    assert [a["status"] for a in answers] == [200, 200], answers
    assert answers[0] == answers[1] == again
