"""kill -9 of the server in the middle of a remote fine-tuning round, then a restart: the round
resumes with the same absolute deadline and the answers given before the kill, the auction
finishes with contiguous iterations, no version or purchase twice, and the same records as the
market replaying the accepted versions; agents on round sockets reconnect and play on."""

from __future__ import annotations

import json
import secrets
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import func, select

from agents.manifest import parse_manifest
from agents.remote import RoundInfo, faithful_fine_tune
from server.cli.launch import ServerProcess
from server.store.db import Database
from server.store.tables import Auction, FineTuneAnswer, FineTuneRound, ModelVersion, Purchase
from sim.market import MarketConfig
from tests.support.databases import fresh_database
from tests.support.factories import honest
from tests.support.processes import server_pair
from tests.support.remote import agents_process, next_round, replay, stalling_agent
from tests.support.server import wait_for

N_PATRONS = 6
HELD_OPEN_S = 120.0
"""The round's deadline: long enough that only the answers close it, before and after the kill."""
TIMEOUT_S = 120


def current(server: ServerProcess, auction_id: int, after: int) -> dict[str, Any]:
    return next_round(server, auction_id, after, TIMEOUT_S)


@dataclass
class RemoteAuction:
    """A remote-mode auction of ``N_PATRONS`` honest patrons, uploading as their agents would."""

    auction_id: int
    ids: list[int]
    manifests: list[dict[str, Any]]
    tokens: list[str]

    @classmethod
    def create(cls, server: ServerProcess, admin: dict[str, str]) -> RemoteAuction:
        manifests = [
            honest(f"kill-{secrets.token_hex(3)}-{i}", seed=600 + i) for i in range(N_PATRONS)
        ]
        submitted = [
            httpx.post(server.url + "/submit", json=m, timeout=30).json() for m in manifests
        ]
        ids = [s["model_id"] for s in submitted]
        body = {
            "n_fish": 1,
            "model_ids": ids,
            "fine_tune_mode": "remote",
            "fine_tune_rounds": 2,
            "round_deadline_s": HELD_OPEN_S,
            "seed": 3,
        }
        created = httpx.post(server.url + "/auctions", json=body, headers=admin, timeout=30)
        tokens = [s["token"] for s in submitted]
        return cls(created.json()["auction_id"], ids, manifests, tokens)

    def upload(self, server: ServerProcess, state: dict[str, Any], model_id: int) -> httpx.Response:
        """The patron's faithful fine-tuning of the open round ``state``, uploaded."""
        position = self.ids.index(model_id)
        tuned = faithful_fine_tune(
            parse_manifest(self.manifests[position]), RoundInfo.from_state(state, position)
        )
        return httpx.put(
            f"{server.url}/auctions/{self.auction_id}/rounds/{state['round']}/models/{model_id}",
            content=tuned.model_dump_json().encode(),
            headers={
                "Authorization": f"Bearer {self.tokens[position]}",
                "Content-Type": "application/json",
            },
            timeout=30,
        )


def check_rows_at_kill(database: Database, auction_id: int) -> None:
    """What the killed server left: the round open with its 2 answers, the auction running."""
    with database.session(write=False) as session:
        round_row = session.scalars(
            select(FineTuneRound).where(FineTuneRound.auction_id == auction_id)
        ).one()
        answered = session.scalar(
            select(func.count()).where(FineTuneAnswer.round_id == round_row.id)
        )
        at_kill = session.scalars(select(Auction).where(Auction.id == auction_id)).one()
    assert round_row.status == "open" and answered == 2
    assert at_kill.status == "running" and at_kill.iteration == 1


def check_stored_once(database: Database, auction: dict[str, Any]) -> None:
    """Each upload stored as one version (the retry included), each purchase once."""
    uploads = sum(
        a["uploaded_id"] is not None for r in auction["fine_tuning"] for a in r["answers"]
    )
    with database.session(write=False) as session:
        versions = session.scalar(
            select(func.count()).where(ModelVersion.auction_id == auction["id"])
        )
        purchases = session.scalar(select(func.count()).where(Purchase.auction_id == auction["id"]))
    assert versions == uploads
    assert purchases == len(auction["buyers"])
    assert len({b["model_id"] for b in auction["buyers"]}) == len(auction["buyers"])


def finished_as_the_market(server: ServerProcess, auction_id: int, seed: int) -> dict[str, Any]:
    """The auction (of one fish and two remote rounds) once over: finished, its iterations
    contiguous, its records those of the market replaying the accepted versions."""
    auction = wait_for(
        lambda: httpx.get(f"{server.url}/auctions/{auction_id}", timeout=30).json(),
        lambda a: a["status"] in ("finished", "failed"),
        TIMEOUT_S,
    )
    assert auction["status"] == "finished", auction["error"]
    history = auction["history"]
    assert [row["iteration"] for row in history] == list(range(len(history)))
    config = MarketConfig(
        n_fish=1, fine_tune=True, fine_tune_rounds=2, seed=seed, fine_tune_mode="remote"
    )
    assert replay(server, auction, config) == history
    return dict(auction)


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.slow)])
def restart_database_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh database per test; PostgreSQL only in the slow run (a long test; a replica's
    kill -9 on PostgreSQL is in the fast run, ``test_replicas.py``)."""
    yield from fresh_database(request.param, tmp_path)


@pytest.mark.slow  # 31 s; the default run keeps test_faults.py's kill -9 with uploads in flight
def test_kill_9_in_the_middle_of_a_round_then_restart(
    restart_database_url: str, tmp_path: Path
) -> None:
    (first, second), admin = server_pair(restart_database_url, tmp_path)
    try:
        first.start()
        remote = RemoteAuction.create(first, admin)
        auction_id = remote.auction_id
        state = current(first, auction_id, after=0)
        assert state["round"] == 1 and state["status"] == "open"
        asked = [i for i in remote.ids if i in state["asked"]]
        assert len(asked) >= 3
        before = {i: remote.upload(first, state, i) for i in asked[:2]}
        assert all(r.status_code == 200 for r in before.values()), [r.text for r in before.values()]
        first.kill()  # the round is open, its other patrons have not answered
        database = Database(restart_database_url)
        check_rows_at_kill(database, auction_id)

        second.start()
        resumed = current(second, auction_id, after=0)
        assert resumed["round"] == 1 and resumed["status"] == "open"
        assert resumed["deadline"] == state["deadline"]  # the same absolute deadline
        assert resumed["rows"] == state["rows"] and resumed["asked"] == state["asked"]
        again = remote.upload(second, resumed, asked[0])  # a retry after the crash: same answer
        assert again.status_code == 200 and again.content == before[asked[0]].content
        for model_id in asked[2:]:
            assert remote.upload(second, resumed, model_id).status_code == 200
        nxt = current(second, auction_id, after=1)  # closed at its last answer
        assert nxt["round"] == 2 and nxt["status"] == "open"
        for model_id in nxt["asked"]:
            assert remote.upload(second, nxt, model_id).status_code == 200
        auction = finished_as_the_market(second, auction_id, seed=3)
        first_round = auction["fine_tuning"][0]
        assert sorted(a["model_id"] for a in first_round["answers"]) == sorted(asked)
        assert all(a["outcome"] in ("accepted", "refused") for a in first_round["answers"])
        check_stored_once(database, auction)
        database.close()
    finally:
        first.kill()
        second.stop()


STALL_S = 4.0
"""How long the stalling socket agent (``STALLING_AGENT``) holds round 1 open."""


@pytest.mark.slow  # the default run keeps its neighbours (docs/development.md)
def test_round_socket_agents_ride_out_a_kill_9_and_restart(tmp_path: Path) -> None:
    """``srd agents --transport websocket`` and a stalling socket agent, the server killed -9
    while round 1 waits for the staller and started again on the same port: every agent
    reconnects, the staller's upload arrives after the restart, the auction finishes with
    contiguous iterations, each upload stored once and the market's records."""
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    (server, _), admin = server_pair(url, tmp_path)
    prefix = f"sock-{secrets.token_hex(3)}"
    processes: list[subprocess.Popen[str]] = []
    try:
        server.start()
        staller = stalling_agent(
            server, f"{prefix}-staller", "websocket", stall_round=1, stall_s=STALL_S
        )
        agents = agents_process(
            server, prefix, "--honest", "5", "--seed", "3", transport="websocket"
        )
        processes = [staller, agents]
        assert staller.stdout is not None
        staller_id = int(staller.stdout.readline().split()[1])
        names = [f"{prefix}-honest-{i:03d}" for i in range(5)]
        found = wait_for(
            lambda: {
                n: httpx.get(f"{server.url}/models", params={"participant": n}).json()["items"]
                for n in names
            },
            lambda by_name: all(by_name.values()),
            TIMEOUT_S,
        )
        ids = [found[n][0]["id"] for n in names] + [staller_id]
        body = {
            "n_fish": 1,
            "model_ids": ids,
            "fine_tune_mode": "remote",
            "fine_tune_rounds": 2,
            "round_deadline_s": HELD_OPEN_S,
            "seed": 4,
        }
        created = httpx.post(server.url + "/auctions", json=body, headers=admin, timeout=30)
        assert created.status_code == 201, created.text
        auction_id = created.json()["auction_id"]
        assert staller.stdout.readline().split() == ["stalling", "1"]
        server.kill()  # round 1 is open: the staller is still fine-tuning
        server.start()  # the same port: the agents' sockets come back to it
        out, err = agents.communicate(timeout=TIMEOUT_S)
        said, _ = staller.communicate(timeout=TIMEOUT_S)
        assert agents.returncode == 0, err
        assert staller.returncode == 0 and said.split()[:2] == ["uploads", "2"], said
        report = json.loads(out)
        assert report["retries"] > 0  # the sockets were opened again after the kill
        auction = finished_as_the_market(server, auction_id, seed=4)
        rounds = auction["fine_tuning"]
        assert [r["round"] for r in rounds] == [1, 2]
        outcomes = [a["outcome"] for r in rounds for a in r["answers"]]
        assert outcomes and set(outcomes) <= {"accepted", "refused"}  # nobody missed a round
        database = Database(url)
        check_stored_once(database, auction)
        database.close()
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.wait()
        server.stop()
