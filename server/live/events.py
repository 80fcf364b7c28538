"""Shared database watchers behind the event streams (``GET /auctions/{id}/events``, ...).

Every event a stream sends is read from committed database rows, never from another process's
memory, so any API replica sharing the database serves the same events. To keep the database
load independent of the number of listeners, a process runs **one** watcher per watched row
(``EventHub.watch``): an asyncio task that polls the row at a short interval while at least one
stream listens, keeps the latest snapshot it read, and wakes every listener when it changes. A
listener then sends from that snapshot whatever its client has not seen yet. When the last
listener leaves (the stream ended or the client disconnected) the task is cancelled.

The number of streams open at once is bounded (``EventHub.acquire``); beyond it the route
answers 503 with ``Retry-After``.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Callable, Hashable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Generic, Protocol, TypeVar

from starlette.concurrency import run_in_threadpool

from server.store.db import is_database_outage, unavailable_message

log = logging.getLogger("srd.events")


class Snapshot(Protocol):
    """What a watcher keeps: its row's state as last read; ``final`` once it can no longer
    change (the auction or job has ended, or the row is gone)."""

    @property
    def final(self) -> bool: ...


S = TypeVar("S", bound=Snapshot)
Poll = Callable[[S | None], S]
"""Read the row's current state, given the previous snapshot (so reads can be incremental);
return that previous snapshot itself when nothing changed."""


@dataclass(eq=False)
class Watch(Generic[S]):
    """One polled row, shared by all its listeners in this process."""

    key: Hashable
    poll: Poll[S]
    interval_s: float
    snapshot: S | None = None
    generation: int = 0  # bumped whenever ``snapshot`` changes
    listeners: int = 0
    _changed: asyncio.Event = field(default_factory=asyncio.Event)
    _task: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"watch {self.key}")

    def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    async def wait(self, generation: int, timeout_s: float) -> bool:
        """Wait until the snapshot is newer than ``generation``; False on timeout."""
        if self.generation != generation:
            return True
        try:
            await asyncio.wait_for(self._changed.wait(), timeout_s)
        except TimeoutError:
            return False
        return True

    def _publish(self, snapshot: S) -> None:
        self.snapshot = snapshot
        self.generation += 1
        woken, self._changed = self._changed, asyncio.Event()
        woken.set()

    async def _run(self) -> None:
        failing = False  # an outage is logged once, not at every poll
        while True:
            try:
                snapshot = await run_in_threadpool(self.poll, self.snapshot)
            except Exception as exc:  # keep the listeners (they get keep-alives), poll again
                if not is_database_outage(exc):
                    log.exception("watching %s failed; retrying", self.key)
                elif not failing:
                    log.warning("watching %s: %s; retrying", self.key, unavailable_message(exc))
                failing = True
            else:
                failing = False
                if snapshot is not self.snapshot:
                    self._publish(snapshot)
                if snapshot.final:
                    return
            await asyncio.sleep(self.interval_s)


class EventHub:
    """This process's watchers, keyed by what they watch, and the open-stream budget."""

    def __init__(self, *, interval_s: float, max_streams: int) -> None:
        self.interval_s = interval_s
        self.max_streams = max_streams
        self.open_streams = 0
        self._watches: dict[Hashable, Watch[Snapshot]] = {}

    def acquire(self) -> bool:
        """Take one stream slot; False when all ``max_streams`` are in use."""
        if self.open_streams >= self.max_streams:
            return False
        self.open_streams += 1
        return True

    def release(self) -> None:
        """Give a stream slot back."""
        self.open_streams -= 1

    @property
    def watched(self) -> int:
        """How many rows are being polled right now."""
        return sum(watch.running for watch in self._watches.values())

    @asynccontextmanager
    async def watch(self, key: Hashable, poll: Poll[S]) -> AsyncIterator[Watch[S]]:
        """Listen to the shared watcher of ``key`` (started on first use), whose first
        snapshot has been read; leaving the block stops it when nobody else listens."""
        existing = self._watches.get(key)
        if existing is None:
            watch: Watch[S] = Watch(key, poll, self.interval_s)
            self._watches[key] = watch  # type: ignore[assignment]
            watch.start()
        else:
            watch = existing  # type: ignore[assignment]
        watch.listeners += 1
        try:
            while watch.snapshot is None:
                await watch.wait(watch.generation, self.interval_s)
            yield watch
        finally:  # no await here: this also runs when the stream's task is cancelled
            watch.listeners -= 1
            if watch.listeners == 0:
                watch.stop()
                del self._watches[key]
