"""A step worker keeps the manifests it parsed from one step to the next, up to 1024 (a bound on
its memory): an auction that makes it forget some of them still finds all of its own patrons.
Before, it forgot every one, this auction's too, and the auction failed with ``KeyError`` (an
outside review: a house past a thousand participants could not run an auction of everyone)."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import httpx
import pytest

from server.cli.launch import ServerProcess, settings_environment
from tests.support.factories import honest
from tests.support.server import ADMIN, QUOTAS_OFF, module_server, wait_for

FIRST = 1000
"""Patrons of the first auction: the worker then keeps nearly its bound."""
NEW = 30
"""New patrons of the second auction, which takes 10 of the first's too: past the bound."""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    env = settings_environment({**QUOTAS_OFF, "auction_workers": 1})  # one worker: one memory
    yield from module_server(tmp_path_factory, "step-memory", env)


def _submitted(client: httpx.Client, names: list[str]) -> list[int]:
    def submit(name: str) -> int:
        answer = client.post("/submit", json=honest(name, seed=len(name)))
        assert answer.status_code == 201 and answer.json()["accepted"], answer.text
        return int(answer.json()["model_id"])

    with ThreadPoolExecutor(8) as pool:  # the screener judges the waiting ones in batches
        return list(pool.map(submit, names))


def _played(client: httpx.Client, model_ids: list[int]) -> dict[str, Any]:
    body = {"n_fish": 5, "model_ids": model_ids, "max_iterations": 3, "seed": 1}
    created = client.post("/auctions", json=body, headers=ADMIN)
    assert created.status_code == 201, created.text
    auction_id = created.json()["auction_id"]
    return wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] not in ("pending", "running"),
        timeout_s=300,
    )


@pytest.mark.slow  # a thousand submissions (15 s): make test-all
def test_an_auction_that_makes_the_worker_forget_still_has_its_patrons(
    server: ServerProcess,
) -> None:
    with httpx.Client(base_url=server.url, timeout=120) as client:
        first = _submitted(client, [f"kept-{i:04d}" for i in range(FIRST)])
        assert _played(client, first)["status"] == "finished"
        new = _submitted(client, [f"new-{i:03d}" for i in range(NEW)])
        second = _played(client, first[:10] + new)
        assert second["status"] == "finished", second.get("error")
        assert second["model_ids"] == first[:10] + new
