"""Screening for ``/submit``, and the uploads of remote rounds, in a dedicated process.

The screener is tensor code: one manifest costs a few milliseconds of mostly fixed overhead,
a batch of sixteen hardly more than two. So the API process hands each manifest to a spawned
screening process (its own interpreter and GIL) over a pipe; that process takes whatever has
queued up since its last pass, and whatever keeps coming within ``GATHER_GAP_S`` of the one
before (at most ``MAX_BATCH``; an upload waits for no company, ``UPLOAD_GAP_S``), judges it
with one ``screener.screen_many`` call (the batched form of ``screener.screen``: same rules,
same verdicts) and sends the verdicts back. Under no load a batch is one manifest, which waits
only the gap for company.

The uploads of remote fine-tuning rounds (``upload``), checked by the API, come the same way:
the process re-screens the new versions of a batch with one ``screener.rescreen_many`` call
(the re-screening the server's own fine-tuning rounds apply), stores the whole batch in one
transaction (``server.remote_rounds.writer.UploadWriter``), rings the rounds' workers and
sends each upload's answer back. The API process writes nothing for an upload (it reads only
what the upload is checked against, ``server.remote_rounds.lookup``).

A screener exception answers that one request with 503 (the batch is re-judged one by one to
find it; an upload it strikes is not stored). If the screening process dies, the requests in
flight fail with ``ScreenerUnavailableError`` (503; an upload may have been stored, and its
repeat gets the stored answer) and a fresh process takes the next ones.

The API's event loop never writes to the pipe itself: a pipe holds a few hundred kilobytes, and
while the screening process is busy (importing torch, judging a burst) a write into a full pipe
would block the whole event loop, every request of the process with it. A sender thread writes
the requests in order; the loop only queues them (at most ``MAX_QUEUED``).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import dataclasses
import itertools
import logging
import multiprocessing
import os
import queue
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

from agents.manifest import Manifest
from screener import Verdict
from server.db import Database
from server.remote_rounds.writer import UploadOutcome, UploadRequest, UploadWriter
from server.workers import die_with_parent, freeze_heap

log = logging.getLogger("srd.screening")

MAX_BATCH = 16  # beyond this the screener's cost per manifest stops falling
GATHER_GAP_S = 0.002
"""A batch being gathered takes the next submission that comes within this long: a burst is
judged in a few batches rather than many small ones, each with the screener's fixed cost; a
lone submission waits this long."""
UPLOAD_GAP_S = 0.0
"""After an upload, a batch takes only what is queued already: a round's uploads come as the API
checks each one, and judging and storing what has come meanwhile keeps the screening process
working alongside the API's checks (rather than idle until the burst has passed), so the last
upload waits for one small batch only."""
VERDICT_TIMEOUT_S = 120.0  # a first request also waits for the process to import torch
MAX_QUEUED = 512
"""Requests written to the pipe by the sender thread, at most this many waiting their turn: a
burst beyond it (a screening process far behind) hears 503 rather than filling memory."""
STOP_GRACE_S = 5.0
RESPAWN_DELAY_S = 0.5  # a process that cannot start must not spin


class ScreenerUnavailableError(RuntimeError):
    """The screening process died or did not answer in time."""


M_TRIM_THRESHOLD = -1  # mallopt parameters (glibc malloc.h)
M_MMAP_THRESHOLD = -3
KEEP_HEAP_BYTES = 128 << 20  # give memory back to the system only above this much free heap
MMAP_ABOVE_BYTES = 32 << 20  # serve allocations below this from the heap, not fresh mmaps


def _keep_heap() -> None:
    """Let glibc reuse freed tensor memory instead of returning it to the kernel and faulting
    it in again on the next batch (a few hundred page faults per batch otherwise)."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None)
        libc.mallopt(M_MMAP_THRESHOLD, MMAP_ABOVE_BYTES)
        libc.mallopt(M_TRIM_THRESHOLD, KEEP_HEAP_BYTES)


_DOOR, _RESCREEN, _UPLOAD = "door", "rescreen", "upload"
"""Kinds of request: a submission's verdict, a fine-tuned version's verdict, an upload."""


def _screening_main(conn: Connection, parent_pid: int, database_url: str | None) -> None:
    die_with_parent(parent_pid)
    _keep_heap()
    import torch

    from screener import rescreen_many, screen_many

    torch.set_num_threads(1)  # tiny tensors: threads only add overhead
    freeze_heap()
    uploads_store = _UploadStore(database_url)
    try:
        while True:
            try:
                batch = gather(conn)
            except EOFError:
                return
            stop = batch[-1] is None  # the stop signal; what came before it is still answered
            if stop:
                batch.pop()
            for kind, judge in ((_DOOR, screen_many), (_RESCREEN, rescreen_many)):
                mine = [(i, Manifest.model_validate_json(m)) for i, k, m in batch if k == kind]
                if mine:
                    answers = [_failed(a) for a in _judge(judge, mine)]
                    conn.send([(i, a) for (i, _), a in zip(mine, answers, strict=True)])
            uploads = [(i, request) for i, k, request in batch if k == _UPLOAD]
            if uploads:
                conn.send(uploads_store.answer(rescreen_many, uploads))
            if stop:
                return
    finally:
        uploads_store.close()


class _UploadStore:
    """The screening process's upload writer, on its own database connection opened at the
    first upload (a process that only screens submissions never opens one)."""

    def __init__(self, database_url: str | None) -> None:
        self._database_url = database_url
        self._database: Database | None = None
        self.writer: UploadWriter | None = None

    def answer(
        self,
        rescreen_many: Callable[[list[Manifest]], list[Verdict]],
        uploads: list[tuple[int, UploadRequest]],
    ) -> list[tuple[int, UploadOutcome | str]]:
        """``_store_uploads``; should anything fail unexpectedly, every upload of the batch
        hears 503 with the error and the process goes on."""
        try:
            if self.writer is None and self._database_url is not None:
                self._database = Database(self._database_url)
                self.writer = UploadWriter(self._database)
            return _store_uploads(self.writer, rescreen_many, uploads)
        except Exception as exc:
            log.exception("a batch of %d uploads failed", len(uploads))
            return [(i, f"the uploads could not be stored: {exc}") for i, _ in uploads]

    def close(self) -> None:
        if self._database is not None:
            self._database.close()


def _store_uploads(
    writer: UploadWriter | None,
    rescreen_many: Callable[[list[Manifest]], list[Verdict]],
    uploads: list[tuple[int, UploadRequest]],
) -> list[tuple[int, UploadOutcome | str]]:
    """Re-screen the new versions among the uploads in one batch, then store every upload the
    screener judged in one group; each one's answer, or the error text of one that was not
    stored."""
    if writer is None:
        return [(i, "the screening process has no database") for i, _ in uploads]
    fresh = [
        (k, Manifest.model_validate_json(request.manifest))
        for k, (_, request) in enumerate(uploads)
        if request.kind == "version" and request.verdict is None and request.manifest is not None
    ]
    requests = [request for _, request in uploads]
    failed: dict[int, str] = {}
    for (k, _), verdict in zip(fresh, _judge(rescreen_many, fresh), strict=True):
        if isinstance(verdict, Verdict):
            requests[k] = dataclasses.replace(requests[k], verdict=verdict)
        else:
            failed[k] = _screener_failed(verdict)
    kept = [k for k in range(len(uploads)) if k not in failed]
    stored = dict(zip(kept, writer.write_group([requests[k] for k in kept]), strict=True))
    return [(i, stored[k] if k in stored else failed[k]) for k, (i, _) in enumerate(uploads)]


def _failed(answer: Verdict | str) -> Verdict | str:
    """A verdict as it is; a screener's error text as the request's 503 message."""
    return answer if isinstance(answer, Verdict) else _screener_failed(answer)


def _screener_failed(error: str) -> str:
    """The 503 message of a request the screener raised on (``_judge``'s error text)."""
    return f"the screener failed: {error}"


def gather(conn: Connection) -> list[Any]:
    """The next batch: the first request (waiting for it), then each one that comes within
    the gap of the one before (``GATHER_GAP_S``; after an upload ``UPLOAD_GAP_S``), up to
    ``MAX_BATCH``; a stop (None) ends the batch."""
    batch = [conn.recv()]
    while len(batch) < MAX_BATCH and batch[-1] is not None and conn.poll(_gap(batch[-1])):
        batch.append(conn.recv())
    return batch


def _gap(request: Any) -> float:
    upload = isinstance(request, tuple) and len(request) == 3 and request[1] == _UPLOAD
    return UPLOAD_GAP_S if upload else GATHER_GAP_S


def _judge(
    screen_many: Callable[[list[Manifest]], list[Verdict]], batch: Sequence[tuple[int, Manifest]]
) -> list[Verdict | str]:
    """Verdicts for a batch; if the screener raises, each manifest alone, errors as text."""
    try:
        return list(screen_many([manifest for _, manifest in batch]))
    except Exception:
        if len(batch) == 1:
            return [traceback.format_exc(limit=-3)]
        return [answer for item in batch for answer in _judge(screen_many, [item])]


@dataclasses.dataclass(frozen=True)
class _Outgoing:
    """A message for the sender thread: a request (id, kind, payload), or the stop (None)."""

    conn: Connection
    message: tuple[int, str, object] | None


class ScreeningService:
    """``await verdict(manifest)`` and ``await upload(request)`` from any event loop; the
    screening (and the storing of uploads, in ``database_url``) runs in a child process."""

    def __init__(self, database_url: str | None = None) -> None:
        self._database_url = database_url
        self._spawn = multiprocessing.get_context("spawn")
        self._ids = itertools.count()
        self._pending: dict[int, Future[Any]] = {}
        self._lock = threading.Lock()  # guards _pending, _conn, _process and sends on the pipe
        self._stopping = False
        self._conn: Connection | None = None
        self._process: BaseProcess | None = None
        self._launched = threading.Event()
        self._outbox: queue.SimpleQueue[_Outgoing | None] = queue.SimpleQueue()
        self._queued = 0  # requests in the outbox, guarded by _lock
        # A pipe is closed only between two writes: a closed descriptor's number may be reused.
        self._writing = threading.Lock()
        self._sender = threading.Thread(target=self._send, name="screening-sender", daemon=True)
        # One long-lived thread starts every screening process and reads its answers: a child's
        # parent-death signal is tied to the thread that started it (see die_with_parent).
        self._keeper = threading.Thread(target=self._keep, name="screening", daemon=True)

    def start(self) -> None:
        """Spawn the screening process (it imports the screener in the background)."""
        self._keeper.start()
        self._sender.start()
        self._launched.wait()

    def _keep(self) -> None:
        while True:
            ours, theirs = multiprocessing.Pipe(duplex=True)
            process = self._spawn.Process(
                target=_screening_main,
                args=(theirs, os.getpid(), self._database_url),
                name="srd-screening",
            )
            process.start()
            theirs.close()
            with self._lock:
                if self._stopping:
                    process.kill()
                    return
                self._conn, self._process = ours, process
            self._launched.set()
            self._read(ours)
            process.join()
            with self._lock:
                failed, self._pending = self._pending, {}
                self._conn = None
                stopping = self._stopping
            for future in failed.values():
                if not future.set_running_or_notify_cancel():
                    continue
                future.set_exception(
                    ScreenerUnavailableError("the screening process exited; retry")
                )
            with self._writing:  # a write in progress fails at once: the process is gone
                ours.close()
            if stopping:
                return
            log.error("the screening process exited (code %s); starting another", process.exitcode)
            time.sleep(RESPAWN_DELAY_S)

    def _ask(self, kind: str, payload: object) -> tuple[int, Future[Any]]:
        """Queue one request for the screening process (the sender thread writes it to the
        pipe); its answer will settle the future."""
        future: Future[Any] = Future()
        with self._lock:
            if self._conn is None:
                raise ScreenerUnavailableError("the screening service is not running")
            if self._queued >= MAX_QUEUED:
                raise ScreenerUnavailableError(
                    f"the screener is {MAX_QUEUED} requests behind; retry shortly"
                )
            request_id = next(self._ids)
            self._pending[request_id] = future
            self._queued += 1
            self._outbox.put(_Outgoing(self._conn, (request_id, kind, payload)))
        return request_id, future

    def _send(self) -> None:
        """Write the queued requests to the pipe, in order, until told to stop (None). A write
        that fails (the process is gone) fails its request."""
        while (outgoing := self._outbox.get()) is not None:
            message = outgoing.message
            try:
                with self._writing:
                    outgoing.conn.send(message)
            except Exception as exc:  # OSError, ValueError: the pipe is closed
                if message is not None:
                    with self._lock:
                        future = self._pending.pop(message[0], None)
                    if future is not None and future.set_running_or_notify_cancel():
                        future.set_exception(
                            ScreenerUnavailableError(f"the screening process is gone: {exc}")
                        )
            finally:
                if message is not None:
                    with self._lock:
                        self._queued -= 1

    async def _answer(self, kind: str, payload: object) -> Any:
        request_id, future = self._ask(kind, payload)
        try:
            return await asyncio.wait_for(asyncio.wrap_future(future), VERDICT_TIMEOUT_S)
        except TimeoutError as exc:
            with self._lock:
                self._pending.pop(request_id, None)
            raise ScreenerUnavailableError("the screener did not answer in time") from exc

    async def verdict(self, manifest: Manifest, *, at_the_door: bool = True) -> Verdict:
        """The screener's verdict on one manifest, awaited on the caller's event loop (no thread
        waits for it): ``screener.screen`` for a submission at the door, or, with
        ``at_the_door=False``, ``screener.rescreen_many``'s judgement of a version fine-tuned
        inside an auction (the same re-screening as the server's own fine-tuning rounds)."""
        verdict: Verdict = await self._answer(
            _DOOR if at_the_door else _RESCREEN, manifest.model_dump_json()
        )
        return verdict

    async def upload(self, request: UploadRequest) -> UploadOutcome:
        """A checked upload re-screened (a new version) and stored with the others of its
        batch, in the screening process; its answer."""
        outcome: UploadOutcome = await self._answer(_UPLOAD, request)
        return outcome

    def _read(self, conn: Connection) -> None:
        """Hand each answer to its waiting request until the pipe closes."""
        while True:
            try:
                answers: list[tuple[int, Any]] = conn.recv()
            except (EOFError, OSError):
                return
            with self._lock:
                resolved = [(self._pending.pop(i, None), answer) for i, answer in answers]
            for future, answer in resolved:
                # None or cancelled: its caller gave up waiting (timed out, or went away)
                if future is None or not future.set_running_or_notify_cancel():
                    continue
                if isinstance(answer, str):
                    future.set_exception(ScreenerUnavailableError(answer))
                else:
                    future.set_result(answer)

    def pid(self) -> int | None:
        """The screening process id (for tests and diagnostics)."""
        with self._lock:
            return None if self._process is None else self._process.pid

    def shutdown(self) -> None:
        """Tell the process to stop (it answers what it holds first) and wait for it; with
        nothing in flight it holds nothing worth waiting for (it may still be importing
        torch), so it is terminated at once."""
        with self._lock:
            self._stopping = True
            conn, process, idle = self._conn, self._process, not self._pending
            if conn is not None and not idle:
                self._outbox.put(_Outgoing(conn, None))  # after the requests queued before it
        self._outbox.put(None)
        if process is not None and idle and process.is_alive():
            process.terminate()
        if process is not None:
            process.join(STOP_GRACE_S)
            if process.is_alive():
                process.kill()
        if self._keeper.is_alive():
            self._keeper.join(STOP_GRACE_S)
        if self._sender.is_alive():
            self._sender.join(STOP_GRACE_S)
