"""Crash safety: kill -9 the real server mid-auction and mid-job, start it again.

The auction (64 patrons, fine-tuning inside the market after each of its first 20 rounds, so
that seconds of rounds remain after the first: with the default 4 the auction could end between
the test seeing its first round and the kill on a busy machine) is killed after a round or two
is committed; the restarted server resumes it from the last checkpoint.
Its full history must equal the same auction played uninterrupted on the market — rounds
contiguous, no purchase lost or doubled, fine-tuned weights and RNG state carried over. The job
runs far longer than the test (minutes), so it is surely running when the kill comes, whatever
the load: the restarted server must re-queue it and run it again (a second attempt), and it is
then cancelled. The workers of the killed server must not outlive it.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import func, select

from agents.manifest import parse_manifest
from screener import screen
from server.cli.launch import ServerProcess
from server.store.db import Database
from server.store.tables import Auction, AuctionIteration, Job, Purchase
from sim.market import Market, MarketConfig
from tests.support.databases import fresh_database
from tests.support.factories import honest
from tests.support.processes import descendants, server_pair
from tests.support.server import wait_for

N_PATRONS = 64
AUCTION = {"n_fish": 1, "fine_tune": True, "fine_tune_rounds": 20, "seed": 0}
JOB = {"kind": "fish", "params": {"steps": 1_000_000, "srd": True}}  # minutes: still running
TIMEOUT_S = 240


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.slow)])
def database_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh database per test; PostgreSQL only in the slow run (a long test)."""
    yield from fresh_database(request.param, tmp_path)


def get(server: ServerProcess, path: str) -> dict[str, Any]:
    response = httpx.get(server.url + path, timeout=30)
    response.raise_for_status()
    return dict(response.json())


def check_rows_at_kill(database: Database, auction_id: int, job_id: int) -> int:
    """What the killed server left: the auction running with a round or more committed, the
    job running in its first attempt. Returns the auction's iteration at the kill."""
    with database.session(write=False) as session:
        at_kill = session.scalars(select(Auction).where(Auction.id == auction_id)).one()
        committed = session.scalar(
            select(func.count()).where(AuctionIteration.auction_id == auction_id)
        )
        job_at_kill = session.scalars(select(Job).where(Job.id == job_id)).one()
    assert at_kill.status == "running" and at_kill.finished_at is None
    assert committed == at_kill.iteration >= 1  # a round or more committed, not finished
    assert job_at_kill.status == "running" and job_at_kill.attempt == 1
    return at_kill.iteration


def check_same_as_uninterrupted(
    auction: dict[str, Any], manifests: list[dict[str, Any]], ids: list[int]
) -> None:
    """The resumed auction's records equal the same auction run without a kill."""
    history = auction["history"]
    config = MarketConfig(
        n_fish=AUCTION["n_fish"],
        fine_tune=True,
        fine_tune_rounds=AUCTION["fine_tune_rounds"],
        seed=AUCTION["seed"],
    )
    market = Market(
        [parse_manifest(m) for m in manifests],
        config,
        rescreen=lambda _i, m: screen(m).accepted,
    )
    records = list(market.run())
    assert [row["price"] for row in history] == [r.price for r in records]
    assert [row["votes"] for row in history] == [r.votes for r in records]
    assert [row["row_votes"] for row in history] == [r.row_votes for r in records]
    assert [(b["model_id"], b["price"]) for b in auction["buyers"]] == [
        (ids[i], price) for r in records for i, price in r.buyers
    ]
    assert auction["quitters"] == [ids[i] for r in records for i in r.quitters]
    assert auction["stop_reason"] == records[-1].stop_reason


def test_kill_9_then_restart_resumes_auction_and_requeues_job(
    database_url: str, tmp_path: Path
) -> None:
    manifests = [honest(f"restart-{i:02d}", seed=200 + i) for i in range(N_PATRONS)]
    # the replay below keeps what the screener accepts: no margin held for an inspector
    (first, second), admin = server_pair(database_url, tmp_path, {"SRD_REVIEW_MARGIN": "0"})
    try:
        first.start()
        with httpx.Client(base_url=first.url, timeout=60) as client:
            answers = [client.post("/submit", json=m) for m in manifests]
            assert all(a.status_code == 201 for a in answers), [a.text for a in answers][:3]
            ids = [a.json()["model_id"] for a in answers]
            job_id = client.post("/jobs", json=JOB, headers=admin).json()["job_id"]
            first_claim = wait_for(
                lambda: get(first, f"/jobs/{job_id}"),
                lambda j: j["status"] == "running",
                TIMEOUT_S,
            )
            body = {**AUCTION, "model_ids": ids}
            auction_id = client.post("/auctions", json=body, headers=admin).json()["auction_id"]
        assert first.process is not None
        state = wait_for(
            lambda: get(first, f"/auctions/{auction_id}"), lambda a: a["iteration"] >= 1, TIMEOUT_S
        )
        workers = descendants(first.process.pid)[1:]
        first.kill()
        assert state["status"] == "running"

        database = Database(database_url)
        iteration_at_kill = check_rows_at_kill(database, auction_id, job_id)
        assert len(workers) >= 3  # screening, auction and job workers (and their fork server)
        wait_for(lambda: {"alive": [p for p in workers if alive(p)]}, lambda s: not s["alive"], 10)

        second.start()
        auction = wait_for(
            lambda: get(second, f"/auctions/{auction_id}"),
            lambda a: a["status"] in ("finished", "failed"),
            TIMEOUT_S,
        )
        again = wait_for(  # claimed again (a new start), or over
            lambda: get(second, f"/jobs/{job_id}"),
            lambda j: (
                (j["status"] == "running" and j["started_at"] != first_claim["started_at"])
                or j["status"] in ("succeeded", "failed")
            ),
            TIMEOUT_S,
        )
        with httpx.Client(base_url=second.url, timeout=60) as client:
            cancelled = client.delete(f"/jobs/{job_id}", headers=admin)
    finally:
        first.kill()
        second.stop()

    assert auction["status"] == "finished", auction["error"]
    history = auction["history"]
    assert [row["iteration"] for row in history] == list(range(len(history)))
    assert len(history) > iteration_at_kill

    check_same_as_uninterrupted(auction, manifests, ids)
    with database.session(write=False) as session:
        purchases = session.scalar(select(func.count()).where(Purchase.auction_id == auction_id))
        rows = session.scalar(select(func.count()).where(AuctionIteration.auction_id == auction_id))
        attempts = session.scalar(select(Job.attempt).where(Job.id == job_id))
    database.close()
    assert purchases == len(auction["buyers"]) and rows == len(history)

    assert again["status"] == "running", again["error"]
    assert attempts == 2  # claimed again after the restart
    assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
