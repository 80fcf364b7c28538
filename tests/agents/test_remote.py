"""The remote agent's client side: retries and giving up, byte counts, the bait-and-switch
upload, faithful fine-tuning, the population's settings."""

from __future__ import annotations

import asyncio
import time
from datetime import UTC, datetime

import httpx
import numpy as np
import pytest
import torch

from agents.batch import from_manifests, to_manifest
from agents.fine_tuning import fine_tune_round
from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from agents.remote import (
    Client,
    PopulationConfig,
    RoundInfo,
    ServerGoneError,
    always_hold,
    faithful_fine_tune,
    population,
)
from agents.remote.client import retry_after_s
from screener import screen
from sim.market import Market, MarketConfig, round_update_problems


def run(handler, call, give_up_s: float = 5.0):
    async def go():
        transport = httpx.MockTransport(handler)
        async with httpx.AsyncClient(transport=transport, base_url="http://auction.test") as http:
            client = Client(http, give_up_s=give_up_s)
            return client, await call(client)

    return asyncio.run(go())


def test_retries_503_and_429_then_counts_the_bodies():
    answers = iter([503, 429, 200])

    def handler(request: httpx.Request) -> httpx.Response:
        status = next(answers)
        headers = {"Retry-After": "0"} if status == 429 else {}
        return httpx.Response(status, json={"ok": status == 200}, headers=headers)

    client, response = run(handler, lambda c: c.request("PUT", "/x", body=b"12345"))
    assert response.status_code == 200
    assert client.traffic.requests == 3 and client.traffic.retries == 2
    assert client.traffic.bytes_up == 15  # the body went three times
    assert client.traffic.bytes_down == len(b'{"ok":false}') * 2 + len(b'{"ok":true}')


def test_gives_up_after_its_time_naming_the_server():
    def handler(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("refused", request=request)

    started = time.monotonic()
    with pytest.raises(ServerGoneError, match=r"http://auction\.test.*gave up after 1 s"):
        run(handler, lambda c: c.request("GET", "/healthz"), give_up_s=1.0)
    assert 0.5 < time.monotonic() - started < 5


@pytest.mark.parametrize("retry_after", ["86400", "30"])
def test_a_retry_after_beyond_the_give_up_time_gives_up_within_it(retry_after):
    """A server that asks for a day (a registration quota spent) or for longer than is left:
    the client keeps to its own give-up time instead of sleeping for what the server asks."""

    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(429, json={"detail": []}, headers={"Retry-After": retry_after})

    started = time.monotonic()
    with pytest.raises(ServerGoneError, match=r"kept answering 429 .*Retry-After: .*gave up"):
        run(handler, lambda c: c.request("POST", "/submit", body=b"{}"), give_up_s=2.0)
    assert time.monotonic() - started < 4


def test_a_request_that_may_have_arrived_is_not_resent_when_asked():
    calls = []

    def handler(request: httpx.Request) -> httpx.Response:
        calls.append(request)
        raise httpx.ReadError("connection reset", request=request)

    with pytest.raises(ServerGoneError, match="ReadError"):
        run(handler, lambda c: c.request("POST", "/submit", body=b"{}", resend=False))
    assert len(calls) == 1


def info_for(position: int = 0, round_: int = 1) -> RoundInfo:
    config = MarketConfig(n_fish=1, fine_tune=True, fine_tune_mode="remote", seed=4)
    rng = np.random.default_rng(0)
    market = Market([honest_manifest(rng, f"h{i}") for i in range(4)], config)
    market.step()
    pending = market.pending_round
    assert pending is not None
    return RoundInfo(
        auction_id=1,
        round=round_,
        iteration=pending.iteration,
        rows=pending.rows,
        fine_tune_seed=pending.fine_tune_seed,
        augmentation_seed=pending.augmentation_seed,
        deadline=datetime.now(UTC),
        seconds_left=10.0,
        position=position,
    )


def test_the_bait_and_switch_keeps_the_design_and_fails_the_screener():
    admitted = honest_manifest(np.random.default_rng(3), "bait")
    assert screen(admitted).accepted
    switched = always_hold(admitted, info_for())
    assert round_update_problems(admitted, switched) == []  # only numbers changed
    assert switched.participant == "bait" and switched != admitted
    verdict = screen(switched)
    assert not verdict.accepted and verdict.reasons


def test_faithful_fine_tuning_moves_only_patrons_with_epochs():
    rng = np.random.default_rng(5)
    manifests = [honest_manifest(rng, f"h{i}") for i in range(12)]
    info = info_for(position=2)
    for manifest in manifests:
        tuned = faithful_fine_tune(manifest, info)
        assert (tuned == manifest) == (manifest.fine_tuning.epochs == 0)
        assert round_update_problems(manifest, tuned) == []
    moving = next(m for m in manifests if m.fine_tuning.epochs > 0)
    other_position = faithful_fine_tune(moving, info_for(position=3))
    assert other_position != faithful_fine_tune(moving, info)  # its seeds depend on its place
    state = {
        "auction_id": 1, "round": 1, "iteration": 0, "rows": [], "fine_tune_seed": 1,
        "augmentation_seed": 2, "deadline": "2026-01-01T00:00:00+00:00", "seconds_left": 1,
    }  # fmt: skip
    assert faithful_fine_tune(moving, RoundInfo.from_state(state, 0)) == moving  # no rows


def test_population_settings_are_checked_and_its_models_are_seeded():
    with pytest.raises(ValueError, match="between 1 and 256"):
        PopulationConfig(server="http://x", honest=200, saboteurs=57)
    with pytest.raises(ValueError, match="name_prefix"):
        PopulationConfig(server="http://x", name_prefix="no spaces")
    config = PopulationConfig(server="http://x", honest=3, saboteurs=2, seed=9, name_prefix="p")
    agents = population(config, [None] * 5)  # type: ignore[list-item]
    again = population(config, [None] * 5)  # type: ignore[list-item]
    assert [a.current for a in agents] == [a.current for a in again]
    assert [a.current.participant for a in agents] == [
        "p-honest-000",
        "p-honest-001",
        "p-honest-002",
        "p-saboteur-003",
        "p-saboteur-004",
    ]
    assert all(screen(a.current).accepted for a in agents[3:])  # honest-looking at first
    assert [a.fine_tuner for a in agents[3:]] == [always_hold, always_hold]


def test_retry_after_is_read_in_seconds_and_never_endless() -> None:
    assert retry_after_s("2") == 2.0 and retry_after_s("0.5") == 0.5
    for header in (None, "", "soon", "-3", "inf", "nan"):
        assert retry_after_s(header) == 0.0, header  # the agent's own backoff applies


@pytest.mark.parametrize("copies", [5, 8])
def test_a_patron_fine_tunes_the_same_alone_and_anywhere_in_a_band(copies: int) -> None:
    """The market fine-tunes the patrons of one padded shape together; each one's result must
    be what it computes alone (a faithful remote agent's), bit for bit, whatever its place in
    the band: with batches that fill their padded rows (15, 16, 32, 63, 64), a patron at an odd
    place had differed in its last bits."""
    rng = np.random.default_rng(5)
    rows = np.tile(np.array([5.0, 1, 1, 1, 0.5, 0.5, 0.5, 0.5]), (64, 1))
    rows[1:, 1:4] += rng.uniform(-0.2, 0.2, (63, 3))
    rows[1:, 7] = rng.uniform(0, 1, 63)
    x = torch.from_numpy(rows)

    def tuning(name: str, seed: int, batch_size: int, epochs: int) -> Manifest:
        m = honest_manifest(np.random.default_rng(seed), name)
        tuned = m.fine_tuning.model_copy(
            update={"batch_size": batch_size, "epochs": epochs, "learning_rate": 5e-5}
        )
        copied = m.augmentation.model_copy(update={"copies": copies})
        return m.model_copy(update={"fine_tuning": tuned, "augmentation": copied})

    def first_after(manifests: list[Manifest]) -> str:
        n = len(manifests)
        seeds = np.full(n, 123, dtype=np.uint64), np.full(n, 456, dtype=np.uint64)
        tuned = fine_tune_round(from_manifests(manifests), x, *seeds, np.arange(3, 3 + n))
        return to_manifest(tuned, 0).model_dump_json()

    for batch_size in (15, 16, 32, 63, 64):
        patron = tuning("p", 1, batch_size, epochs=1)
        alone = first_after([patron])
        for band in (2, 3, 4):  # the others take more steps: the patron sorts last
            others = [
                tuning(f"o{j}", 10 + j, ((batch_size - 1) // 16) * 16 + 1, epochs=3)
                for j in range(band - 1)
            ]
            assert first_after([patron, *others]) == alone, (batch_size, band)
