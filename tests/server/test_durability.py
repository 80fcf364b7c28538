"""Acknowledged means stored: under a load of concurrent submissions (through the group-commit
writer) the server is killed with SIGKILL; after a restart every submission that got 201 is
there with the id, participant and version it was given, and none that got an error answer is.
Submissions whose answer was lost in the crash may be either way."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from server.cli.launch import ServerProcess, settings_environment
from server.store.db import Database
from server.store.tables import ModelVersion, Participant
from tests.support.factories import honest
from tests.support.server import QUOTAS_OFF

CLIENTS = 8
ACKNOWLEDGED_BEFORE_KILL = 40
"""The kill comes once this many submissions were acknowledged, the clients still sending."""
LOAD_LIMIT_S = 60.0


@pytest.mark.postgres_in_slow_run
def test_every_201_survives_a_kill_9(fresh_database_url: str, tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    env = settings_environment(QUOTAS_OFF)
    server = ServerProcess(database_url=fresh_database_url, data_dir=data_dir, extra_env=env)
    acknowledged: list[dict[str, Any]] = []
    refused: list[str] = []
    lost: list[str] = []
    stop = threading.Event()
    lock = threading.Lock()

    def client(number: int) -> None:
        with httpx.Client(base_url=server.url, timeout=10) as http:
            sent = 0
            while not stop.is_set():
                name = f"durable-{number}-{sent}"
                sent += 1
                try:
                    answer = http.post("/submit", json=honest(name, seed=sent))
                except httpx.TransportError:
                    with lock:
                        lost.append(name)
                    return
                with lock:
                    if answer.status_code == 201:
                        acknowledged.append(answer.json())
                    else:
                        refused.append(name)

    try:
        server.start()
        warm = httpx.post(server.url + "/submit", json=honest("durable-warm-up"), timeout=120)
        assert warm.status_code == 201  # the screening process is up
        threads = [threading.Thread(target=client, args=(i,)) for i in range(CLIENTS)]
        for thread in threads:
            thread.start()
        deadline = time.monotonic() + LOAD_LIMIT_S
        while len(acknowledged) < ACKNOWLEDGED_BEFORE_KILL and time.monotonic() < deadline:
            time.sleep(0.01)
        server.kill()  # while the clients are still sending
        stop.set()
        for thread in threads:
            thread.join(30)
        server.start()  # the restart recovers the database
        assert httpx.get(server.url + "/healthz", timeout=10).status_code == 200
    finally:
        server.stop()

    assert len(acknowledged) >= ACKNOWLEDGED_BEFORE_KILL, "the load never got going"
    assert lost, "the kill came after the load: nothing was in flight"
    database = Database(fresh_database_url)
    with database.session(write=False) as session:
        stored = {
            row.id: (row.name, row.version)
            for row in session.execute(
                select(ModelVersion.id, Participant.name, ModelVersion.version).join(Participant)
            )
        }
    database.close()
    for answer in acknowledged:
        assert stored.get(answer["model_id"]) == (answer["participant"], answer["version"])
    print(  # the figures of docs/server.md (pytest -s)
        f"acknowledged {len(acknowledged)}, refused {len(refused)}, answer lost {len(lost)}, "
        f"stored {len(stored)}: every acknowledged one stored, none of the refused"
    )
    names = {name for name, _ in stored.values()}
    assert not names & set(refused)
    assert len(stored) <= len(acknowledged) + len(lost) + 1  # + the warm-up
