"""Helpers for tests against a live ``srd serve``: the quick start's population, a Server-Sent
Events reader, and an auction played at a set pace so a test can watch it run."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest

import sim.market
from server.auctions.steps import base_price, run_step
from server.store import crud
from server.store.db import Database
from server.store.status import AUCTION_UNFINISHED
from server.store.tables import utcnow
from server.work.pool import WorkerContext
from sim.market import Market

POPULATION = Path(__file__).resolve().parents[2] / "examples" / "population"
TEST_OWNER = "tests"
"""The lease owner of rows a test plays itself (no server claims them)."""


def submit_population(client: httpx.Client) -> dict[str, dict[str, Any]]:
    """Submit every manifest of ``examples/population``; file stem → the /submit answer."""
    answers = {}
    for path in sorted(POPULATION.glob("*.json")):
        response = client.post(
            "/submit", content=path.read_bytes(), headers={"Content-Type": "application/json"}
        )
        assert response.status_code == 201, response.text
        answers[path.stem] = response.json()
    return answers


def sse_events(response: httpx.Response) -> Iterator[dict[str, str]]:
    """The events of a ``text/event-stream`` response as ``{field: value}`` (a comment-only
    block gives ``{"comment": ...}``), until the server closes the stream."""
    event: dict[str, str] = {}
    for line in response.iter_lines():
        if not line:
            if event:
                yield event
            event = {}
            continue
        field, _, value = line.partition(":")
        value = value.removeprefix(" ")
        key = field or "comment"
        event[key] = f"{event[key]}\n{value}" if key in event else value
    if event:
        yield event


def data(event: dict[str, str]) -> Any:
    """An event's JSON payload."""
    return json.loads(event["data"])


class PacedMarket(Market):
    """The market, waiting ``pace_s`` before each round (set on the class by ``paced_auction``)."""

    pace_s = 0.0

    def step(self) -> Any:
        time.sleep(self.pace_s)
        return super().step()


def create_unstarted_auction(
    database_url: str, model_ids: list[int], *, n_fish: int, seed: int
) -> int:
    """An auction row written as ``POST /auctions`` writes it, but leased to the test (for a
    day), so no server claims it: it stays pending until a test drives it."""
    database = Database(database_url)
    try:
        with database.session(write=True) as session:
            auction = crud.create_auction(
                session,
                model_ids=model_ids,
                n_fish=n_fish,
                rarity=None,
                max_iterations=64,
                fine_tune=False,
                seed=seed,
                opening_price=base_price(),
            )
            auction.lease_owner, auction.lease_expires = TEST_OWNER, utcnow() + timedelta(days=1)
            session.commit()
            return auction.id
    finally:
        database.close()


def play_to_end(context: WorkerContext, auction_id: int, most: int = 1000) -> int:
    """Run the auction's steps one after another, as the worker pool would, until it has
    ended (a step plays at most ``STEP_SLICE_S``); how many steps it took."""
    database = Database(context.database_url)
    try:
        for steps in range(1, most + 1):
            run_step(context, auction_id)
            with database.session(write=False) as session:
                state = crud.step_state(session, auction_id=auction_id)
                if state is None or state[0].status not in AUCTION_UNFINISHED:
                    return steps
        raise AssertionError(f"auction {auction_id} did not end in {most} steps")
    finally:
        database.close()


@contextmanager
def paced_auction(
    monkeypatch: pytest.MonkeyPatch,
    database_url: str,
    data_dir: Path,
    auction_id: int,
    *,
    pace_s: float,
) -> Iterator[threading.Thread]:
    """Play an unstarted auction with the server's own worker code (``run_step``: the real
    market, the real per-round commits) in a thread of the test process, one round every
    ``pace_s``. The API process only reads what it commits, as it would from a worker."""
    monkeypatch.setattr(PacedMarket, "pace_s", pace_s)
    monkeypatch.setattr(sim.market, "Market", PacedMarket)  # what the worker imports
    context = WorkerContext(
        database_url=database_url, data_dir=str(data_dir), progress_interval_s=0.1, torch_threads=1
    )
    thread = threading.Thread(target=play_to_end, args=(context, auction_id), daemon=True)
    thread.start()
    try:
        yield thread
    finally:
        thread.join(timeout=120)
        assert not thread.is_alive(), "the paced auction did not finish"
