"""A remote upload's deadline is judged when its last byte reached the server, not when the API
gets round to its route: an upload pipelined behind a long poll (HTTP/1.1 answers a
connection's requests in order, so its route runs only once the poll has answered) ends the
poll at once and counts as in time, and one sent after the deadline is still late; an upload
read before a ``kill -9`` but not stored counts as in time on its retry after the restart."""

from __future__ import annotations

import contextlib
import json
import shutil
import socket
import sqlite3
import threading
import time
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import pytest

from agents.manifest import parse_manifest
from agents.remote.fine_tuners import RoundInfo, faithful_fine_tune
from server.cli.launch import ServerProcess, settings_environment
from tests.server.test_remote_protocol import open_round, put, start_remote
from tests.support.remote import honest_remote_auction, next_round
from tests.support.server import ADMIN_TOKEN, QUOTAS_OFF, module_server

POLL_S = 30
"""How long the long poll ahead of the upload would hold the connection: past the deadline and
its grace, had the upload not ended it."""


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


def test_an_upload_pipelined_behind_a_long_poll_ends_the_poll_and_counts_in_time(
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
    # Uploads under made-up tokens are refused and never journaled (they would fill it).
    journal = server.data_dir / "arrivals"
    before = sum(f.stat().st_size for f in journal.glob("*.log"))
    made_up = b"".join(
        _put_request(path.format(early), f"srdp_made-up-{n:02d}", _new_weights(manifest))
        for n in range(20)
    )
    assert set(_statuses(server, made_up, 20)) == {403}
    assert sum(f.stat().st_size for f in journal.glob("*.log")) == before
    pipelined = poll + _put_request(path.format(early), token, _new_weights(manifest))
    time.sleep(max(0.0, deadline - 1.0 - time.time()))
    written = time.time()
    assert written < deadline - 0.5, "too slow to set the race up"
    assert _statuses(server, pipelined, 2) == [200, 200]  # the poll, then the upload: in time
    assert time.time() - written < POLL_S / 2  # the poll did not wait its 30 s
    assert sum(f.stat().st_size for f in journal.glob("*.log")) > before  # journaled
    token, manifest = patrons[late]
    time.sleep(max(0.0, deadline + 0.1 - time.time()))
    late_put = _put_request(path.format(late), token, _new_weights(manifest))
    assert _statuses(server, late_put, 1) == [410]  # after the deadline: late, grace or not
    next_round(server, auction_id, 1, 60)
    auction = httpx.get(f"{server.url}/auctions/{auction_id}", timeout=30).json()
    outcomes = {a["model_id"]: a["outcome"] for a in auction["fine_tuning"][0]["answers"]}
    assert outcomes[early] in ("accepted", "refused", "held") and outcomes[late] == "late"


KILL_ROUND_S = 12.0
"""The round's deadline in the kill test: the upload hangs on the write lock, the server is
killed, the deadline passes while it is down."""


@pytest.mark.parametrize(
    "journal", [True, pytest.param(False, marks=pytest.mark.slow)], ids=["journal", "control"]
)
def test_an_upload_read_before_a_kill_9_counts_on_its_retry_after_the_deadline(
    tmp_path: Path, journal: bool
) -> None:
    """An upload's body was read and checked, but another process held SQLite's write lock, so
    it was not stored when the server was killed (-9). The server restarts after the round's
    deadline; the agent's retry of the same bytes is judged by the first arrival: accepted, and
    the round waits for it. With the journal removed before the restart (the control) the
    retry is late."""
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    lives = [
        ServerProcess(
            database_url=url,
            data_dir=tmp_path / "data",
            admin_token=ADMIN_TOKEN,
            extra_env=settings_environment(QUOTAS_OFF),
            log_path=tmp_path / f"serve-{n}.log",
        )
        for n in range(2)
    ]
    lives[0].start()
    with httpx.Client(base_url=lives[0].url, timeout=60) as client:
        auction_id, manifests, patrons = start_remote(
            client, "kill-arrival", 740, 3, round_deadline_s=KILL_ROUND_S, seed=5
        )
        state = open_round(client, auction_id)
    assert state["status"] == "open" and state["round"] == 1, state
    position = next(i for i, (m, _) in enumerate(patrons) if m in state["asked"])
    model_id, token = patrons[position]
    info = RoundInfo.from_state(state, position)
    body = faithful_fine_tune(parse_manifest(manifests[position]), info).model_dump_json()
    deadline = time.monotonic() + state["seconds_left"]
    url_of_upload = f"{lives[0].url}/auctions/{auction_id}/rounds/1/models/{model_id}"
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}

    def send() -> None:
        with contextlib.suppress(httpx.HTTPError):  # the server is killed under it
            httpx.put(url_of_upload, content=body, headers=headers, timeout=60)

    holder = sqlite3.connect(tmp_path / "srd.db", isolation_level=None, check_same_thread=False)
    holder.execute("BEGIN IMMEDIATE")  # as another writer would: the upload waits for it
    try:
        threading.Thread(target=send, daemon=True).start()
        time.sleep(1.0)  # read, checked, journaled; waiting on the lock
        assert time.monotonic() < deadline - 3, "the upload came too late to test"
        lives[0].kill()
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    if not journal:
        shutil.rmtree(tmp_path / "data" / "arrivals")
    time.sleep(max(0.0, deadline + 1.0 - time.monotonic()))  # down past the deadline
    with lives[1], httpx.Client(base_url=lives[1].url, timeout=60) as client:
        retry = put(client, auction_id, 1, model_id, body.encode(), token)
        if journal:
            assert retry.status_code == 200, retry.text
            assert retry.json()["outcome"] == "accepted", retry.text
        else:
            assert retry.status_code == 410, retry.text
