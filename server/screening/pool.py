"""The screener pool: verdicts for ``/submit`` and for the uploads of remote rounds, in a
dedicated process that never touches the database.

The screener is tensor code: one manifest costs a few milliseconds of mostly fixed overhead,
a batch of sixteen hardly more than two. So the API process hands each manifest to a
screening process (its own interpreter and GIL) over a pipe; that process takes whatever has
queued up since its last pass, and whatever keeps coming within ``GATHER_GAP_S`` of the one
before (at most ``MAX_BATCH``), judges it with one ``screener.screen_many`` (at the door) or
``screener.rescreen_many`` (a fine-tuned version) call, which give each manifest the verdict it
would get alone, and sends the verdicts back. The API stores every upload and every verdict
itself (``server.services``); the screening process only judges.

A client (a ``/submit``'s address) has at most ``SCREENINGS_PER_CLIENT`` requests at the
screening process at once; its others wait their turn in the API (``_Turns``), so one client's
backlog of costly manifests does not stand in front of everyone else's.

A screener exception answers that one request with 503 (the batch is re-judged one by one to
find it). If the screening process dies, the requests in flight fail with
``ScreenerUnavailableError`` (503) and a fresh process takes the next ones.

The API's event loop never writes to the pipe itself: a pipe holds a few hundred kilobytes, and
while the screening process is busy (importing torch, judging a burst) a write into a full pipe
would block the whole event loop. A sender thread writes the requests in order; the loop only
queues them (at most ``MAX_QUEUED``).
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
from collections.abc import AsyncIterator, Callable, Sequence
from concurrent.futures import Future
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any

from agents.manifest import Manifest
from screener import Verdict
from server.work.pool import adopt_environment, die_with_parent, freeze_heap, process_context

log = logging.getLogger("srd.screening")

MAX_BATCH = 16  # beyond this the screener's cost per manifest stops falling
GATHER_GAP_S = 0.002
"""A batch being gathered takes the next submission that comes within this long: a burst is
judged in a few batches rather than many small ones, each with the screener's fixed cost; a
lone submission waits this long."""
VERDICT_TIMEOUT_S = 120.0  # a first request also waits for the process to import torch
MAX_QUEUED = 512
"""Requests written to the pipe by the sender thread, at most this many waiting their turn: a
burst beyond it (a screening process far behind) hears 503 rather than filling memory."""
STOP_GRACE_S = 5.0
SCREENINGS_PER_CLIENT = 4
"""A client's (a ``/submit``'s address's) requests the API waits on at the screening process at
once (one it stopped waiting for, after ``VERDICT_TIMEOUT_S``, no longer counts, though the
process may still judge it); its others wait their turn in the API. So a client that submits
costly manifests in bulk (16 noisy copies fine-tuned 4 epochs at batch 1: 20 times an honest
one's screening) delays another's verdict by a few of its own, not by its whole backlog,
whatever number of tokens it registered."""
RESPAWN_DELAY_S = 0.5  # a process that cannot start must not spin
MAX_RESPAWN_DELAY_S = 30.0
"""A process the system refuses to start (no memory, a process limit) is tried again after
twice the delay each time, up to this: the screener comes back by itself, and the log does
not fill."""
STALL_S = 30.0
"""The screener counts as stalled (``/healthz`` not ready) when it has held requests this long
without answering any: its warm-up takes seconds, a batch milliseconds."""


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


_DOOR, _RESCREEN = "door", "rescreen"
"""Kinds of request: a submission's verdict, a fine-tuned version's verdict."""


def _screening_main(conn: Connection, parent_pid: int, environ: dict[str, str]) -> None:
    die_with_parent(parent_pid)
    adopt_environment(environ)
    _keep_heap()
    import torch

    from screener import rescreen_many, screen_many

    torch.set_num_threads(1)  # tiny tensors: threads only add overhead
    freeze_heap()
    while True:
        try:
            batch = gather(conn)
        except EOFError:
            return
        stop = batch[-1] is None  # the stop signal; what came before it is still answered
        if stop:
            batch.pop()
        # A round's uploads first: they have a deadline, and their agents wait on them.
        for kind, judge in ((_RESCREEN, rescreen_many), (_DOOR, screen_many)):
            mine = [(i, Manifest.model_validate_json(m)) for i, k, m in batch if k == kind]
            if mine:
                answers = [_failed(a) for a in _judge(judge, mine)]
                conn.send([(i, a) for (i, _), a in zip(mine, answers, strict=True)])
        if stop:
            return


def _failed(answer: Verdict | str) -> Verdict | str:
    """A verdict as it is; a screener's error text as the request's 503 message."""
    return answer if isinstance(answer, Verdict) else _screener_failed(answer)


def _screener_failed(error: str) -> str:
    """The 503 message of a request the screener raised on (``_judge``'s error text)."""
    return f"the screener failed: {error}"


def gather(conn: Connection) -> list[Any]:
    """The next batch: the first request (waiting for it), then each one that comes within
    ``GATHER_GAP_S`` of the one before, up to ``MAX_BATCH``; a stop (None) ends the batch."""
    batch = [conn.recv()]
    while len(batch) < MAX_BATCH and batch[-1] is not None and conn.poll(GATHER_GAP_S):
        batch.append(conn.recv())
    return batch


def _judge(
    screen_many: Callable[[list[Manifest]], list[Verdict]], batch: Sequence[tuple[int, Manifest]]
) -> list[Verdict | str]:
    """Verdicts for a batch; if the screener raises, each manifest alone, errors as text: the
    exception's line (the answer's 503 says it; its frames go to the log, not to clients)."""
    try:
        return list(screen_many([manifest for _, manifest in batch]))
    except Exception as exc:
        if len(batch) == 1:
            log.error("the screener failed on a manifest:\n%s", traceback.format_exc(limit=-3))
            return [f"{type(exc).__name__}: {exc}"]
        return [answer for item in batch for answer in _judge(screen_many, [item])]


@dataclasses.dataclass(frozen=True)
class _Outgoing:
    """A message for the sender thread: a request (id, kind, payload), or the stop (None)."""

    conn: Connection
    message: tuple[int, str, object] | None


def _fail(futures: dict[int, Future[Any]], why: str) -> None:
    """Answer requests that will get no verdict with 503 (``why``)."""
    for future in futures.values():
        if future.set_running_or_notify_cancel():
            future.set_exception(ScreenerUnavailableError(why))


class _Turns:
    """Each client's turns at the screening process: at most ``share`` at once, the others
    waiting in order (an asyncio semaphore per client with requests, on the API's loop)."""

    def __init__(self, share: int) -> None:
        self._share = share
        self._clients: dict[str, tuple[asyncio.Semaphore, int]] = {}
        """Per client with requests: its semaphore and how many requests hold or await it."""

    @contextlib.asynccontextmanager
    async def turn(self, client: str | None) -> AsyncIterator[None]:
        if client is None:
            yield
            return
        semaphore, users = self._clients.get(client) or (asyncio.Semaphore(self._share), 0)
        self._clients[client] = (semaphore, users + 1)
        try:
            try:
                async with asyncio.timeout(VERDICT_TIMEOUT_S):
                    await semaphore.acquire()
            except TimeoutError as exc:
                raise ScreenerUnavailableError(
                    f"{self._share} screenings of this client's were ahead of it for "
                    f"{VERDICT_TIMEOUT_S:g} s; retry later"
                ) from exc
            try:
                yield
            finally:
                semaphore.release()
        finally:
            semaphore, users = self._clients[client]
            if users == 1:
                del self._clients[client]
            else:
                self._clients[client] = (semaphore, users - 1)


class ScreeningService:
    """``await verdict(manifest)`` from any event loop; the screening runs in a child process."""

    def __init__(self) -> None:
        self._process_context = process_context()
        self._ids = itertools.count()
        self._pending: dict[int, Future[Any]] = {}
        self._lock = threading.Lock()  # guards _pending, _conn, _process and sends on the pipe
        self._stopping = False
        self._process: BaseProcess | None = None
        self._turns = _Turns(SCREENINGS_PER_CLIENT)
        self._outbox: queue.SimpleQueue[_Outgoing | None] = queue.SimpleQueue()
        self._queued = 0  # requests in the outbox, guarded by _lock
        # When the screener last made progress: answered, or got work while it had none.
        self._progress_at = time.monotonic()  # guarded by _lock
        self._gave_up = False  # a request timed out since the last answer, guarded by _lock
        # A pipe is closed only between two writes: a closed descriptor's number may be reused.
        self._writing = threading.Lock()
        self._sender = threading.Thread(target=self._send, name="screening-sender", daemon=True)
        # The first process's pipe exists from the start: requests made while that process
        # starts wait in it (or in the outbox) instead of being refused.
        ours, theirs = multiprocessing.Pipe(duplex=True)
        self._conn: Connection | None = ours
        # One long-lived thread starts every screening process and reads its answers: a child's
        # parent-death signal is tied to the thread that started it (see die_with_parent).
        self._keeper = threading.Thread(
            target=self._keep, args=(ours, theirs), name="screening", daemon=True
        )

    def start(self) -> None:
        """Start the screening process in the background and return at once: its first start
        also starts the fork server, which imports torch (a few seconds); requests made
        meanwhile wait for it."""
        self._keeper.start()
        self._sender.start()

    def _keep(self, ours: Connection, theirs: Connection) -> None:
        refused = 0  # starts refused in a row
        while True:
            process = self._process_context.Process(
                target=_screening_main,
                args=(theirs, os.getpid(), dict(os.environ)),
                name="srd-screening",
            )
            try:
                process.start()
            except (OSError, EOFError) as exc:  # no process now (EAGAIN, ENOMEM, the fork server)
                refused += 1
                delay = min(RESPAWN_DELAY_S * 2**refused, MAX_RESPAWN_DELAY_S)
                log.error("starting the screening process failed (%s); again in %g s", exc, delay)
                with self._lock:
                    stopping = self._stopping
                    if stopping:
                        failed, self._pending = self._pending, {}
                if stopping:
                    _fail(failed, "the server is stopping")
                    return
                time.sleep(delay)  # requests meanwhile wait in the pipe, or hear 503
                continue
            refused = 0
            theirs.close()
            with self._lock:
                stopping = self._stopping
                if stopping:
                    failed, self._pending = self._pending, {}
                else:
                    self._conn, self._process = ours, process
                    self._progress_at, self._gave_up = time.monotonic(), False
            if stopping:
                process.kill()
                _fail(failed, "the server is stopping")
                return
            self._read(ours)
            process.join()
            with self._lock:
                failed, self._pending = self._pending, {}
                self._conn = None
                stopping = self._stopping
            _fail(failed, "the screening process exited; retry")
            with self._writing:  # a write in progress fails at once: the process is gone
                ours.close()
            if stopping:
                return
            log.error("the screening process exited (code %s); starting another", process.exitcode)
            time.sleep(RESPAWN_DELAY_S)
            ours, theirs = multiprocessing.Pipe(duplex=True)

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
            if not self._pending and not self._gave_up:
                self._progress_at = time.monotonic()
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
            async with asyncio.timeout(VERDICT_TIMEOUT_S):  # wait_for (3.11) can swallow a cancel
                return await asyncio.wrap_future(future)
        except TimeoutError as exc:
            with self._lock:
                self._pending.pop(request_id, None)
                self._gave_up = True
            raise ScreenerUnavailableError("the screener did not answer in time") from exc

    async def verdict(
        self,
        manifest: Manifest,
        *,
        at_the_door: bool = True,
        manifest_json: str | None = None,
        client: str | None = None,
    ) -> Verdict:
        """The screener's verdict on one manifest, awaited on the caller's event loop (no thread
        waits for it): ``screener.screen`` for a submission at the door, or, with
        ``at_the_door=False``, ``screener.rescreen_many``'s judgement of a version fine-tuned
        inside an auction (the same re-screening as the server's own fine-tuning rounds).
        ``manifest_json``: the manifest's ``model_dump_json()``, if the caller has it already.
        ``client``: whose request it is; a client has at most ``SCREENINGS_PER_CLIENT`` at the
        screening process, its others wait their turn (within ``VERDICT_TIMEOUT_S``)."""
        if manifest_json is None:
            manifest_json = manifest.model_dump_json()
        kind = _DOOR if at_the_door else _RESCREEN
        async with self._turns.turn(client):
            verdict: Verdict = await self._answer(kind, manifest_json)
        return verdict

    def _read(self, conn: Connection) -> None:
        """Hand each answer to its waiting request until the pipe closes."""
        while True:
            try:
                answers: list[tuple[int, Any]] = conn.recv()
            except (EOFError, OSError):
                return
            with self._lock:
                resolved = [(self._pending.pop(i, None), answer) for i, answer in answers]
                self._progress_at, self._gave_up = time.monotonic(), False
            for future, answer in resolved:
                # None or cancelled: its caller gave up waiting (timed out, or went away)
                if future is None or not future.set_running_or_notify_cancel():
                    continue
                if isinstance(answer, str):
                    future.set_exception(ScreenerUnavailableError(answer))
                else:
                    future.set_result(answer)

    def problem(self) -> str | None:
        """Why the screener cannot judge submissions now (for ``/healthz``), or None: its
        process is gone and not yet started again, or it has held requests ``STALL_S`` without
        answering any (hung, or stopped)."""
        with self._lock:
            if self._stopping:
                return "the screener is stopping"
            if self._conn is None:
                return "the screening process exited and is starting again"
            idle_s = time.monotonic() - self._progress_at
            if (self._pending or self._gave_up) and idle_s > STALL_S:
                return f"the screener has answered no request for {idle_s:.0f} s"
        return None

    def pid(self) -> int | None:
        """The screening process id (for tests and diagnostics)."""
        with self._lock:
            return None if self._process is None else self._process.pid

    def shutdown(self) -> None:
        """Tell the process to stop (it answers what it holds first) and wait for it; with
        nothing in flight it holds nothing worth waiting for, so it is terminated at once. One
        not started yet (the fork server is still importing torch) is not waited for."""
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
        if process is not None and self._keeper.is_alive():
            # (a keeper still starting the first process kills it itself once it has started)
            self._keeper.join(STOP_GRACE_S)
        if self._sender.is_alive():
            self._sender.join(STOP_GRACE_S)
