"""A remote upload's deadline is judged when its last byte reached the server, not when a busy
API gets round to its route: an upload whose route is held past the deadline (here by its
address's request rate, which paces it half a second) still counts as in time, and one sent
after the deadline is still late."""

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

RATE_PER_S = 2
"""The request rate per address: a bucket of 8 (4 s of it), then one request every 0.5 s."""
PACED = "127.0.0.9"
"""The address whose upload waits for its turn."""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    env = {"SRD_LIMIT_ADDRESS_REQUESTS_PER_S": str(RATE_PER_S)}
    yield from module_server(tmp_path_factory, "arrival", env)


def _raw_put(server: ServerProcess, path: str, token: str, body: bytes, *, source: str) -> int:
    """PUT the body in one write from ``source``; the answer's status."""
    request = (
        f"PUT {path} HTTP/1.1\r\nHost: test\r\nAuthorization: Bearer {token}\r\n"
        f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
        "Connection: close\r\n\r\n"
    ).encode() + body
    address = ("127.0.0.1", server.port)
    with socket.create_connection(address, timeout=60, source_address=(source, 0)) as sock:
        sock.sendall(request)
        answer = b""
        while b"\r\n" not in answer and (chunk := sock.recv(4096)):
            answer += chunk
    return int(answer.split(b" ", 2)[1])


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
    time.sleep(max(0.0, deadline - 0.35 - time.time()))
    transport = httpx.HTTPTransport(local_address=PACED)
    with httpx.Client(base_url=server.url, transport=transport, timeout=30) as paced:
        for _ in range(4 * RATE_PER_S):  # the address's bucket, emptied
            paced.get("/healthz")
    written = time.time()
    assert written < deadline - 0.1, "too slow to set the race up"
    token, manifest = patrons[early]
    status = _raw_put(server, path.format(early), token, _new_weights(manifest), source=PACED)
    assert time.time() > deadline  # its route ran after the deadline: the rate held it
    assert status == 200
    token, manifest = patrons[late]
    time.sleep(max(0.0, deadline + 0.1 - time.time()))
    status = _raw_put(server, path.format(late), token, _new_weights(manifest), source="127.0.0.1")
    assert status == 410  # sent after the deadline: late, even within the close's grace
    closed = next_round(server, auction_id, 1, 60)
    auction = httpx.get(f"{server.url}/auctions/{auction_id}", timeout=30).json()
    outcomes = {a["model_id"]: a["outcome"] for a in auction["fine_tuning"][0]["answers"]}
    assert outcomes[early] in ("accepted", "refused", "held") and outcomes[late] == "late"
    assert closed["auction_status"] in ("running", "finished"), closed
