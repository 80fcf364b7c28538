"""The screening service: verdicts awaited on an event loop, and callers that stop waiting."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

import numpy as np
import pytest

from agents.negotiator import honest_manifest, saboteur_manifest
from screener import screen
from server.screening import ScreeningService


@pytest.fixture(scope="module")
def service() -> Iterator[ScreeningService]:
    screening = ScreeningService()
    screening.start()
    yield screening
    screening.shutdown()


def test_verdicts_are_the_screeners_own(service: ScreeningService) -> None:
    rng = np.random.default_rng(3)
    manifests = [honest_manifest(rng, "h"), saboteur_manifest(rng, "s")]

    async def ask() -> list[object]:
        return list(await asyncio.gather(*(service.verdict(m) for m in manifests)))

    assert asyncio.run(ask()) == [screen(m) for m in manifests]


def test_a_caller_that_stops_waiting_leaves_the_service_working(
    service: ScreeningService,
) -> None:
    """A cancelled wait (a client gone, a request timed out) must not break the thread that
    hands out answers: the next verdicts still arrive."""
    rng = np.random.default_rng(4)
    honest = honest_manifest(rng, "h")

    async def cancel_some_then_ask() -> object:
        waits = [asyncio.create_task(service.verdict(honest)) for _ in range(8)]
        await asyncio.sleep(0)
        for wait in waits:
            wait.cancel()
        await asyncio.gather(*waits, return_exceptions=True)
        await asyncio.sleep(0.5)  # their answers come back to nobody
        return await asyncio.wait_for(service.verdict(honest), 60)

    assert asyncio.run(cancel_some_then_ask()) == screen(honest)
