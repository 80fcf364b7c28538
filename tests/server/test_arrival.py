"""A remote upload's deadline is judged when its last byte reached the server, not when the API
gets round to its route: an upload pipelined behind a long poll (HTTP/1.1 answers a
connection's requests in order, so its route runs only once the poll has answered, after the
deadline) still counts as in time, and one sent after the deadline is still late."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator
from datetime import datetime
from typing import Any

import httpx
import pytest

from server.cli.launch import ServerProcess
from tests.support.remote import honest_remote_auction, next_round
from tests.support.server import module_server

POLL_S = 0.4
"""How long the long poll ahead of the upload holds the connection."""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    yield from module_server(tmp_path_factory, "arrival")


def _put_request(path: str, token: str, body: bytes) -> bytes:
    return (
        f"PUT {path} HTTP/1.1\r\nHost: test\r\nAuthorization: Bearer {token}\r\n"
        f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n\r\n"
    ).encode() + body


def _statuses(server: ServerProcess, requests: bytes, count: int) -> list[int]:
    """Write the requests in one go on one connection; the status of each of ``count``
    answers, in order."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=60) as sock:
        sock.sendall(requests)
        statuses: list[int] = []
        with sock.makefile("rb") as answers:
            while len(statuses) < count:
                status = int(answers.readline().split(b" ", 2)[1])
                length = 0
                while (line := answers.readline()) not in (b"\r\n", b""):
                    name, _, value = line.partition(b":")
                    if name.strip().lower() == b"content-length":
                        length = int(value)
                answers.read(length)
                statuses.append(status)
    return statuses


def _new_weights(manifest: dict[str, Any]) -> bytes:
    manifest = json.loads(json.dumps(manifest))
    manifest["decision"]["B"]["bias"] += 1e-6
    return json.dumps(manifest).encode()


def test_an_upload_in_by_the_deadline_counts_though_its_route_runs_after_it(
    server: ServerProcess,
) -> None:
    auction_id, entered = honest_remote_auction(
        server, range(300, 304), name="arrival", n_fish=1, fine_tune_rounds=1,
        round_deadline_s=4, seed=3,
    )  # fmt: skip
    state = next_round(server, auction_id, 0, 60)
    assert state["status"] == "open" and len(state["asked"]) >= 2, state
    patrons = {model_id: (token, manifest) for model_id, token, manifest in entered}
    early, late = state["asked"][:2]
    deadline = datetime.fromisoformat(state["deadline"].replace("Z", "+00:00")).timestamp()
    path = f"/auctions/{auction_id}/rounds/1/models/{{}}"
    poll = (
        f"GET /auctions/{auction_id}/rounds/current?wait={POLL_S}&after=1 HTTP/1.1\r\n"
        "Host: test\r\n\r\n"
    ).encode()
    token, manifest = patrons[early]
    pipelined = poll + _put_request(path.format(early), token, _new_weights(manifest))
    time.sleep(max(0.0, deadline - 0.3 - time.time()))  # the upload runs 0.1 s past it
    written = time.time()
    assert written < deadline - 0.1, "too slow to set the race up"
    assert _statuses(server, pipelined, 2) == [200, 200]  # the poll, then the upload: in time
    assert time.time() > deadline  # the upload's route ran after the poll, past the deadline
    token, manifest = patrons[late]
    time.sleep(max(0.0, deadline + 0.1 - time.time()))
    late_put = _put_request(path.format(late), token, _new_weights(manifest))
    assert _statuses(server, late_put, 1) == [410]  # after the deadline: late, grace or not
    next_round(server, auction_id, 1, 60)
    auction = httpx.get(f"{server.url}/auctions/{auction_id}", timeout=30).json()
    outcomes = {a["model_id"]: a["outcome"] for a in auction["fine_tuning"][0]["answers"]}
    assert outcomes[early] in ("accepted", "refused", "held") and outcomes[late] == "late"
