"""Remote fine-tuning end to end over real HTTP: ``srd serve`` in a subprocess (SQLite and
PostgreSQL), ``srd agents`` with honest and bait-and-switch agents, an agent killed with
SIGKILL in the middle of a round, and the same auction played in the server and remotely, by
long poll and PUT and over round sockets. The agents' end-to-end run uses round sockets on
SQLite and HTTP on PostgreSQL (each transport once)."""

from __future__ import annotations

import asyncio
import json
import secrets
import signal
from collections.abc import Iterator
from datetime import datetime
from typing import Any

import httpx
import numpy as np
import pytest

from agents.batch import from_manifests
from agents.manifest import Manifest, parse_manifest
from agents.remote import Client, RemoteAgent, Transport
from server.cli.launch import ServerProcess
from sim.market import MarketConfig
from tests.support.databases import fresh_database
from tests.support.factories import honest
from tests.support.remote import agents_process, replay, stalling_agent
from tests.support.server import wait_for

DEADLINE_S = 3.0
"""Round deadline of the end-to-end auction (the killed agent's round waits this long)."""
TIMEOUT_S = 180


@pytest.fixture(
    scope="module",
    # PostgreSQL only in the slow run (29 s): the storage tests cover its side of the rounds
    params=["sqlite", pytest.param("postgresql", marks=[pytest.mark.postgres, pytest.mark.slow])],
)
def server(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[ServerProcess]:
    data_dir = tmp_path_factory.mktemp("remote")
    for url in fresh_database(request.param, data_dir):
        token = secrets.token_hex(16)
        with ServerProcess(database_url=url, data_dir=data_dir, admin_token=token) as process:
            yield process


def get(server: ServerProcess, path: str, **params: Any) -> Any:
    response = httpx.get(server.url + path, params=params, timeout=30)
    response.raise_for_status()
    return response.json()


def admin(server: ServerProcess) -> dict[str, str]:
    return {"Authorization": f"Bearer {server.admin_token}"}


def transport_of(server: ServerProcess) -> str:
    """The transport of the agents' end-to-end run on this server's database."""
    return "websocket" if server.database_url.startswith("sqlite") else "http"


def play_with_agents_and_a_victim(server: ServerProcess) -> tuple[int, int, set[int], Any]:
    """``srd agents`` (6 honest, 2 bait-and-switch) and a victim agent (``STALLING_AGENT``)
    that is killed -9 in its round-2 fine-tuning, in one remote auction: (auction id, victim's
    model id, saboteur model ids, the agents' --json report)."""
    prefix = f"e2e-{secrets.token_hex(3)}"
    victim_name = f"{prefix}-victim"
    transport = transport_of(server)
    victim = stalling_agent(server, victim_name, transport, stall_round=2, stall_s=3600)
    agents = agents_process(
        server, prefix, "--honest", "6", "--saboteurs", "2", "--seed", "7", transport=transport
    )
    try:
        assert victim.stdout is not None
        victim_id = int(victim.stdout.readline().split()[1])
        names = [f"{prefix}-honest-{i:03d}" for i in range(6)]
        names += [f"{prefix}-saboteur-{i:03d}" for i in range(6, 8)]
        found = wait_for(
            lambda: {n: get(server, "/models", participant=n)["items"] for n in names},
            lambda by_name: all(by_name.values()),
            TIMEOUT_S,
        )
        ids = [found[n][0]["id"] for n in names]
        saboteurs = set(ids[6:])
        body = {
            "n_fish": 1,
            "model_ids": [*ids, victim_id],
            "fine_tune_mode": "remote",
            "fine_tune_rounds": 3,
            "round_deadline_s": DEADLINE_S,
            "seed": 11,
        }
        created = httpx.post(server.url + "/auctions", json=body, headers=admin(server))
        assert created.status_code == 201, created.text
        auction_id = created.json()["auction_id"]
        said = victim.stdout.readline().split()
        assert said == ["stalling", "2"], f"the victim did not reach round 2: {said}"
        victim.send_signal(signal.SIGKILL)  # in the middle of its round-2 fine-tuning
        victim.wait()
        out, err = agents.communicate(timeout=TIMEOUT_S)
    finally:
        for process in (victim, agents):
            if process.poll() is None:
                process.kill()
                process.wait()
    assert agents.returncode == 0, err
    return auction_id, victim_id, saboteurs, json.loads(out)


def check_answers(server: ServerProcess, auction_id: int, saboteurs: set[int], report: Any) -> None:
    """Bait-and-switch uploads refused (stored with reasons, version 1 bids on); honest ones
    accepted as versions of their round; the report counts them."""
    rounds = get(server, f"/auctions/{auction_id}")["fine_tuning"]
    answers = [(r, a) for r in rounds for a in r["answers"]]
    sabotage = [a for _, a in answers if a["model_id"] in saboteurs]
    assert sabotage and all(a["outcome"] == "refused" and a["version"] == 1 for a in sabotage)
    assert report["uploads"]["refused"] >= len(sabotage)
    for a in sabotage:  # stored as a rejected version with reasons; the admitted one bids on
        refused = get(server, f"/models/{a['uploaded_id']}")
        assert refused["accepted"] is False and refused["reasons"]
        assert refused["parent_id"] == a["model_id"] and a["version_id"] == a["model_id"]
        assert refused["patron_id"] == a["model_id"]  # the version it bids for
    new_versions = [
        a for _, a in answers if a["model_id"] not in saboteurs and a["uploaded_id"] is not None
    ]
    accepted = [a for a in new_versions if a["outcome"] == "accepted"]
    assert accepted and all(a["version"] >= 2 for a in accepted)
    for round_, a in ((r, a) for r, a in answers if a in accepted):
        version = get(server, f"/models/{a['version_id']}")
        assert version["round"] == round_["round"] and version["auction_id"] == auction_id
        # the patron it bids for, whichever earlier upload it was fine-tuned from
        assert version["patron_id"] == a["model_id"]
    assert report["uploads"]["accepted"] >= len(accepted)


@pytest.mark.slow  # the default run keeps its neighbours (docs/development.md)
@pytest.mark.postgres_in_slow_run
def test_honest_and_bait_and_switch_agents_and_a_killed_one(server: ServerProcess) -> None:
    auction_id, victim_id, saboteurs, report = play_with_agents_and_a_victim(server)
    auction = get(server, f"/auctions/{auction_id}")
    assert auction["status"] == "finished", auction["error"]
    history = auction["history"]
    assert [row["iteration"] for row in history] == list(range(len(history)))
    rounds = auction["fine_tuning"]
    assert [r["round"] for r in rounds] == [1, 2, 3][: len(rounds)] and len(rounds) >= 2
    assert report["agents"] == 8 and report["auctions"] == [auction_id]
    assert report["transport"] == transport_of(server)
    assert report["uploads"]["late"] == 0 and report["bytes_up"] > 0 and report["bytes_down"] > 0

    check_answers(server, auction_id, saboteurs, report)
    by_round = {r["round"]: {a["model_id"]: a for a in r["answers"]} for r in rounds}
    assert by_round[1][victim_id]["outcome"] == "accepted"
    assert by_round[2][victim_id]["outcome"] == "missing"
    assert all(a["outcome"] == "missing" for a in [by_round.get(3, {}).get(victim_id)] if a)
    waited = [seconds(r["closed_at"]) - seconds(r["opened_at"]) for r in rounds]
    assert waited[0] < DEADLINE_S  # everyone answered: closed at the last upload
    assert DEADLINE_S <= waited[1] < DEADLINE_S + 2  # the dead agent: closed at the deadline
    assert all(r["bytes_total"] > r["bytes_published"] > 0 for r in rounds)

    config = MarketConfig(
        n_fish=1, fine_tune=True, fine_tune_rounds=3, seed=11, fine_tune_mode="remote"
    )
    assert replay(server, auction, config) == history  # the accepted versions bid


def seconds(stamp: str) -> float:
    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


@pytest.mark.parametrize(("transport", "rows"), [("http", 64), ("websocket", 16)])
def test_faithful_remote_agents_replay_the_server_auction(
    server: ServerProcess, transport: Transport, rows: int
) -> None:
    """... with the reference's 64 item rows, and with the paper's 16 (``rows``)."""
    manifests = [honest(f"same-{secrets.token_hex(3)}-{i}", seed=500 + i) for i in range(8)]
    submitted = [httpx.post(server.url + "/submit", json=m, timeout=30).json() for m in manifests]
    ids = [s["model_id"] for s in submitted]
    assert all(s["accepted"] for s in submitted)
    common = {"n_fish": 2, "model_ids": ids, "fine_tune_rounds": 3, "seed": 21, "rows": rows}
    in_server = httpx.post(
        server.url + "/auctions", json={**common, "fine_tune": True}, headers=admin(server)
    ).json()["auction_id"]
    remote = httpx.post(
        server.url + "/auctions",
        json={**common, "fine_tune_mode": "remote", "round_deadline_s": 60},
        headers=admin(server),
    ).json()["auction_id"]

    async def play() -> None:
        async with httpx.AsyncClient(base_url=server.url) as http:
            client = Client(http)
            agents = [
                RemoteAgent(
                    client,
                    parse_manifest(m),
                    token=s["token"],
                    model_id=s["model_id"],
                    transport=transport,
                )
                for m, s in zip(manifests, submitted, strict=True)
            ]
            await asyncio.gather(*(agent.play(remote) for agent in agents))

    asyncio.run(play())
    done = {
        a: wait_for(
            lambda a=a: get(server, f"/auctions/{a}"),
            lambda s: s["status"] in ("finished", "failed"),
            TIMEOUT_S,
        )
        for a in (in_server, remote)
    }
    mine, theirs = done[remote], done[in_server]
    assert mine["status"] == theirs["status"] == "finished"
    assert mine["rows"] == theirs["rows"] == rows
    first = theirs["history"][0]  # scored on every row (a fine-tuning follows it)
    assert sum(first["row_votes"].values()) == rows * sum(first["votes"].values())
    assert mine["history"] == theirs["history"]
    assert mine["buyers"] == theirs["buyers"] and mine["quitters"] == theirs["quitters"]
    assert mine["stop_reason"] == theirs["stop_reason"]
    assert len(mine["fine_tuning"]) >= 2
    assert all(a["outcome"] != "missing" for r in mine["fine_tuning"] for a in r["answers"])
    # Every vote's weights, through the API: each remote patron's uploaded version against the
    # weights the in-server market fine-tuned it to, iteration by iteration, bit for bit.
    tuned = 0
    for row in theirs["history"]:
        n = row["iteration"]
        for vote in get(server, f"/auctions/{in_server}/iterations/{n}/votes")["votes"]:
            weights = f"/iterations/{n}/votes/{vote['model_id']}/weights"
            here = get(server, f"/auctions/{in_server}{weights}")
            there = get(server, f"/auctions/{remote}{weights}")
            assert there["fine_tuned_after"] is None  # a remote patron bids with its uploads
            assert (there["version_id"] != vote["model_id"]) == (
                here["fine_tuned_after"] is not None
            )
            pair = [parse_manifest(here["manifest"])], [parse_manifest(there["manifest"])]
            assert max_difference(*pair) == 0.0, (n, vote["model_id"])
            tuned += here["fine_tuned_after"] is not None
            if there["version_id"] != vote["model_id"]:  # a path naming the version is told so
                wrong = httpx.get(
                    f"{server.url}/auctions/{remote}/iterations/{n}/votes/{there['version_id']}"
                )
                assert wrong.status_code == 404
                assert f"the version patron {vote['model_id']} bid with" in wrong.text
    assert tuned  # fine-tuning changed someone


def max_difference(a: list[Manifest], b: list[Manifest]) -> float:
    left, right = from_manifests(a).parameters(), from_manifests(b).parameters()
    return max(float(np.abs((left[k] - right[k]).numpy()).max()) for k in left)
