"""The screening service: verdicts awaited on an event loop, and callers that stop waiting."""

from __future__ import annotations

import asyncio
import dataclasses
import multiprocessing
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from agents.manifest import Manifest
from agents.negotiator import honest_manifest, saboteur_manifest
from screener import Verdict, rescreen_many, screen
from server.remote_rounds import UploadRequest
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


def test_asking_never_waits_for_a_full_pipe(monkeypatch: pytest.MonkeyPatch) -> None:
    """The event loop only queues a request: with a screening process that does not read (its
    pipe full), asking returns at once and the sender thread writes the requests in order as
    the pipe drains; past ``MAX_QUEUED`` requests waiting their turn the screener is "behind"
    (503); a request whose pipe has closed fails as the process being gone."""
    import server.screening as screening

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
    from server.screening import GATHER_GAP_S, MAX_BATCH, gather

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


def test_uploads_are_batched_with_what_is_queued_only() -> None:
    """After an upload the batch takes only what has queued up already: the screening process
    works on a round's uploads alongside the API's checks instead of waiting out the burst."""
    from server.screening import GATHER_GAP_S, UPLOAD_GAP_S, gather

    assert UPLOAD_GAP_S < GATHER_GAP_S
    up = [(0, "upload", "a"), (1, "upload", "b"), (2, "upload", "c")]
    queued = _Arrivals([(0.0, up[0]), (0.0, up[1]), (GATHER_GAP_S / 2, up[2])])
    assert gather(queued) == up[:2]  # type: ignore[arg-type]
    assert gather(queued) == up[2:]  # type: ignore[arg-type]


def _upload(**changes: Any) -> UploadRequest:
    """A new version's upload to round 1 (id 7) of auction 1, by patron 0."""
    base = UploadRequest(
        kind="version",
        round_number=1,
        round_id=7,
        position=0,
        participant_id=1,
        current_id=1,
        current_version=1,
        auction_id=1,
        body_sha256="0" * 64,
        bytes_in=1,
    )
    return dataclasses.replace(base, **changes)


class _Writer:
    """Records the groups it is asked to store; answers each upload with its position."""

    def __init__(self) -> None:
        self.groups: list[list[UploadRequest]] = []

    def write_group(self, group: list[UploadRequest]) -> list[object]:
        self.groups.append(group)
        return [f"stored {request.position}" for request in group]


def test_an_upload_the_screener_fails_on_is_not_stored_and_the_rest_are() -> None:
    """The new versions of a batch are re-screened together; one the screener raises on is
    answered with the error (a 503 for its agent, who may send it again) and left out of the
    group the writer stores, with the verdicts of the others attached."""
    from server.db import JSONText
    from server.screening import _store_uploads

    rng = np.random.default_rng(3)
    models = [honest_manifest(rng, f"u-{k}") for k in range(3)]
    base = _upload()
    uploads = [
        (10 + k, dataclasses.replace(base, position=k, manifest=JSONText(m.model_dump_json())))
        for k, m in enumerate(models)
    ]
    uploads.append((13, dataclasses.replace(base, kind="unchanged", position=3)))

    def fails_on_the_second(manifests: list[Manifest]) -> list[Verdict]:
        if any(m.participant == "u-1" for m in manifests):
            raise RuntimeError("boom")
        return rescreen_many(manifests)

    writer = _Writer()
    answers = _store_uploads(writer, fails_on_the_second, uploads)  # type: ignore[arg-type]
    assert [i for i, _ in answers] == [10, 11, 12, 13]
    assert answers[0][1] == "stored 0" and answers[2][1] == "stored 2"
    assert answers[3][1] == "stored 3"
    assert isinstance(answers[1][1], str) and answers[1][1].startswith("the screener failed:")
    assert "boom" in answers[1][1]
    (group,) = writer.groups
    assert [r.position for r in group] == [0, 2, 3]
    expected = rescreen_many([models[0], models[2]])
    assert [r.verdict for r in group] == [*expected, None]


def test_a_batch_of_uploads_that_fails_unexpectedly_answers_each_with_the_error() -> None:
    """Anything the upload store did not foresee (here an upload whose manifest is not JSON,
    which the API never sends) answers every upload of the batch with the error (a 503 for its
    agent) instead of ending the screening process; nothing of the batch is stored."""
    from server.db import JSONText
    from server.screening import _UploadStore

    request = _upload(manifest=JSONText("{not json"))
    store = _UploadStore(None)
    writer = _Writer()
    store.writer = writer  # type: ignore[assignment]
    answers = store.answer(rescreen_many, [(5, request), (6, dataclasses.replace(request))])
    assert [i for i, _ in answers] == [5, 6]
    for _, answer in answers:
        assert isinstance(answer, str) and answer.startswith("the uploads could not be stored")
    assert writer.groups == []
