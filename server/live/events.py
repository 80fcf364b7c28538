"""The event streams' share of live updates (``GET /auctions/{id}/events``, ...): they listen
to this process's live-update source (``server.live.source``), so the database load does not
grow with the number of streams, and the number open at once is bounded (``EventHub.acquire``;
beyond it the route answers 503 with ``Retry-After``).
"""

from __future__ import annotations

from contextlib import AbstractAsyncContextManager

from server.live.source import Feed, LiveSource, S, View
from server.store import crud


class EventHub:
    """The open-stream budget, and the feeds the streams listen to."""

    def __init__(self, source: LiveSource, *, max_streams: int) -> None:
        self.source = source
        self.max_streams = max_streams
        self.open_streams = 0

    def acquire(self, *, reserved: bool = False) -> bool:
        """Take one stream slot; False when all ``max_streams`` are in use, unless ``reserved``
        (the operator's, bounded by its client share)."""
        if self.open_streams >= self.max_streams and not reserved:
            return False
        self.open_streams += 1
        return True

    def release(self) -> None:
        """Give a stream slot back."""
        self.open_streams -= 1

    def watch(
        self, kind: crud.LiveKind, row_id: int, view: View[S]
    ) -> AbstractAsyncContextManager[Feed[S]]:
        """The feed of ``view`` on the row (``LiveSource.watch``)."""
        return self.source.watch(kind, row_id, view)
