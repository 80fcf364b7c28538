"""The screening service: verdicts awaited on an event loop, and callers that stop waiting."""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import signal
import threading
from collections.abc import Iterator

import numpy as np
import pytest

from agents.negotiator import honest_manifest, saboteur_manifest
from screener import rescreen_many, screen
from server.screening.pool import SCREENINGS_PER_CLIENT, ScreeningService
from tests.support.processes import refuse_starts


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


def test_fine_tuned_uploads_get_the_in_auction_re_screening(service: ScreeningService) -> None:
    """Submissions at the door and versions fine-tuned inside an auction, mixed in one batch,
    each get their own judgement: ``screen`` (with the projection of its own fine-tuning) and
    ``rescreen_many`` (the server's re-screening of every fine-tuning round)."""
    rng = np.random.default_rng(5)
    manifests = [honest_manifest(rng, f"h{i}") for i in range(4)] + [saboteur_manifest(rng, "s")]
    doors = [True, False, True, False, False]

    async def ask() -> list[object]:
        return list(
            await asyncio.gather(
                *(service.verdict(m, at_the_door=d) for m, d in zip(manifests, doors, strict=True))
            )
        )

    expected = [
        screen(m) if door else rescreen_many([m])[0]
        for m, door in zip(manifests, doors, strict=True)
    ]
    assert asyncio.run(ask()) == expected
    assert expected[-1].accepted is False


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


def test_a_client_with_a_backlog_delays_another_by_its_share_not_its_backlog(
    service: ScreeningService,
) -> None:
    """With the screening process stopped, one client asks 40 verdicts, then another asks one:
    once the process goes on, the second client's is answered with the first's first few (its
    share at the process), not after all 40 (two and a half batches later, first come first
    served)."""
    rng = np.random.default_rng(6)
    honest = honest_manifest(rng, "h")

    async def ask() -> list[str]:
        await service.verdict(honest)  # the process is up and has imported the screener
        pid = service.pid()
        assert pid is not None
        answered: list[str] = []

        async def one(client: str) -> None:
            await service.verdict(honest, client=client)
            answered.append(client)

        os.kill(pid, signal.SIGSTOP)
        try:
            backlog = [asyncio.create_task(one("a")) for _ in range(40)]
            await asyncio.sleep(0.2)  # all 40 asked: SCREENINGS_PER_CLIENT of them sent
            other = asyncio.create_task(one("b"))
            await asyncio.sleep(0.2)
        finally:
            os.kill(pid, signal.SIGCONT)
        await asyncio.wait_for(asyncio.gather(*backlog, other), 120)
        return answered

    answered = asyncio.run(ask())
    assert answered.count("a") == 40
    assert answered.index("b") <= SCREENINGS_PER_CLIENT, answered


def test_asking_never_waits_for_a_full_pipe(monkeypatch: pytest.MonkeyPatch) -> None:
    """The event loop only queues a request: with a screening process that does not read (its
    pipe full), asking returns at once and the sender thread writes the requests in order as
    the pipe drains; past ``MAX_QUEUED`` requests waiting their turn the screener is "behind"
    (503); a request whose pipe has closed fails as the process being gone."""
    import server.screening.pool as screening

    monkeypatch.setattr(screening, "MAX_QUEUED", 16)
    service = ScreeningService()
    ours, theirs = multiprocessing.Pipe(duplex=True)
    service._conn = ours  # nobody reads it yet
    service._sender.start()
    payload = "x" * 65_536  # a few of them fill the pipe
    asked: list[int] = []
    refused: list[str] = []

    def ask_until_refused() -> None:
        try:
            for _ in range(64):
                asked.append(service._ask("door", payload)[0])
        except screening.ScreenerUnavailableError as exc:
            refused.append(str(exc))

    asking = threading.Thread(target=ask_until_refused)
    asking.start()
    asking.join(30)
    assert not asking.is_alive()
    assert refused == ["the screener is 16 requests behind; retry shortly"]
    assert 16 <= len(asked) < 64  # 16 waiting, and the few the pipe took before it was full
    assert [theirs.recv()[0] for _ in asked] == asked  # written in order once read
    theirs.close()
    _, future = service._ask("door", payload)
    with pytest.raises(screening.ScreenerUnavailableError, match="gone"):
        future.result(timeout=30)
    service._outbox.put(None)
    service._sender.join(30)
    ours.close()


def test_a_screening_process_the_system_refuses_to_start_is_tried_again(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A fork the system refuses (EAGAIN: a process limit; ENOMEM) is tried again, later each
    time: a request made meanwhile gets its verdict once a process starts (before, the thread
    that starts them died, and the server screened nothing until it was restarted)."""
    refusals = refuse_starts(monkeypatch, "srd-screening", 2)
    manifest = honest_manifest(np.random.default_rng(3), "h")
    service = ScreeningService()
    with caplog.at_level(logging.ERROR, logger="srd.screening"):
        service.start()
        try:
            assert asyncio.run(service.verdict(manifest)) == screen(manifest)
        finally:
            service.shutdown()
    assert not refusals
    failed = [r.getMessage() for r in caplog.records if "failed" in r.getMessage()]
    assert failed == [
        "starting the screening process failed ([Errno 11] Resource temporarily unavailable); "
        f"again in {delay:g} s"
        for delay in (1, 2)
    ]


class _Arrivals:
    """A pipe end whose requests arrive at scripted times (seconds from the first recv)."""

    def __init__(self, arrivals: list[tuple[float, object]]) -> None:
        self.arrivals = arrivals
        self.now = 0.0

    def recv(self) -> object:
        at, item = self.arrivals.pop(0)
        self.now = max(self.now, at)
        return item

    def poll(self, timeout: float) -> bool:
        if self.arrivals and self.arrivals[0][0] <= self.now + timeout:
            return True
        self.now += timeout
        return False


def test_a_burst_is_gathered_into_one_batch_and_a_stop_ends_it() -> None:
    """Submissions that keep coming within the gap join the batch being gathered; a pause
    longer than the gap, a full batch or a stop closes it."""
    from server.screening.pool import GATHER_GAP_S, MAX_BATCH, gather

    gap = GATHER_GAP_S
    burst = [(k * gap * 0.5, k) for k in range(5)] + [(10 * gap, "later")]
    pipe = _Arrivals(burst)
    assert gather(pipe) == [0, 1, 2, 3, 4]  # type: ignore[arg-type]
    assert gather(pipe) == ["later"]  # type: ignore[arg-type]
    many = _Arrivals([(0.0, k) for k in range(MAX_BATCH + 3)])
    assert len(gather(many)) == MAX_BATCH  # type: ignore[arg-type]
    assert len(gather(many)) == 3  # type: ignore[arg-type]
    stopping = _Arrivals([(0.0, "a"), (0.0, None), (0.0, "after")])
    assert gather(stopping) == ["a", None]  # type: ignore[arg-type]
