"""How soon a round committed by another process reaches an agent's long poll.

A real ``srd serve`` on a throw-away database; this script plays the worker: it opens
fine-tuning round k of an auction in one transaction (the round row, the auction's
``updated_at`` and, on PostgreSQL, ``NOTIFY``) while a long poll
(``GET /auctions/{id}/rounds/current?wait=10&after=k-1``) waits, and measures the time from the
commit's return to the long poll's answer.

Run: ``.venv/bin/python -m benchmarks.live_latency [--backend sqlite|postgresql] [--rounds N]``
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time
from contextlib import ExitStack
from datetime import timedelta
from pathlib import Path

import httpx
from sqlalchemy import func, insert, select, update

from server.cli.launch import ServerProcess
from server.store.db import Database
from server.store.tables import Auction, FineTuneRound, utcnow
from tests.support.databases import postgres_admin_url, throwaway_postgres
from tests.support.live import create_unstarted_auction, submit_population
from tests.support.server import ADMIN_TOKEN

CHANNEL = "srd_live"  # server.store.crud.live.LIVE_CHANNEL (written out: older trees lack it)


def open_round(database: Database, auction_id: int, number: int) -> float:
    """Commit round ``number`` of the auction, open; the time the commit returned."""
    with database.session(write=True) as session:
        now = utcnow()
        session.execute(
            insert(FineTuneRound).values(
                auction_id=auction_id,
                round=number,
                iteration=number - 1,
                status="open",
                opened_at=now,
                deadline=now + timedelta(seconds=60),
                rows=[[0.0] * 4],
                fine_tune_seed=number,
                augmentation_seed=number,
                asked=[0],
                bytes_published=0,
            )
        )
        session.execute(update(Auction).where(Auction.id == auction_id).values(updated_at=now))
        if not database.url.startswith("sqlite"):
            session.execute(select(func.pg_notify(CHANNEL, f"auction:{auction_id}")))
        session.commit()
    return time.monotonic()


def long_poll(client: httpx.Client, auction_id: int, after: int, answered: list[float]) -> None:
    """Wait for a round above ``after``; note when the answer came."""
    answer = client.get(
        f"/auctions/{auction_id}/rounds/current", params={"wait": 10, "after": after}
    )
    answered.append(time.monotonic())
    assert answer.json()["round"] == after + 1, answer.text


def measure(url: str, rounds: int) -> list[float]:
    """Milliseconds from each round's commit to the waiting long poll's answer."""
    delays = []
    with (
        tempfile.TemporaryDirectory() as data_dir,
        ServerProcess(database_url=url, data_dir=Path(data_dir), admin_token=ADMIN_TOKEN) as server,
        httpx.Client(base_url=server.url, timeout=30) as client,
    ):
        patrons = [a["model_id"] for a in submit_population(client).values() if a["accepted"]]
        auction_id = create_unstarted_auction(url, patrons, n_fish=1, seed=0)
        database = Database(url)
        try:
            for number in range(1, rounds + 1):
                answered: list[float] = []
                waiter = threading.Thread(
                    target=long_poll, args=(client, auction_id, number - 1, answered)
                )
                waiter.start()
                time.sleep(0.3)  # the long poll waits by now
                committed = open_round(database, auction_id, number)
                waiter.join(15)
                delays.append((answered[0] - committed) * 1000)
        finally:
            database.close()
    return delays


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", choices=["sqlite", "postgresql"], default="postgresql")
    parser.add_argument("--rounds", type=int, default=30)
    args = parser.parse_args()
    with ExitStack() as stack:
        if args.backend == "sqlite":
            folder = stack.enter_context(tempfile.TemporaryDirectory())
            url = f"sqlite:///{folder}/srd.db"
        else:
            admin = postgres_admin_url()
            if admin is None:
                raise SystemExit("PostgreSQL is not reachable on 127.0.0.1:5432")
            url = stack.enter_context(throwaway_postgres(admin))
        delays = sorted(measure(url, args.rounds))
    p90 = delays[int(0.9 * (len(delays) - 1))]
    print(
        f"{args.backend}: {len(delays)} rounds, commit → long-poll answer: "
        f"median {statistics.median(delays):.1f} ms, p90 {p90:.1f} ms, "
        f"min {delays[0]:.1f} ms, max {delays[-1]:.1f} ms"
    )


if __name__ == "__main__":
    main()
