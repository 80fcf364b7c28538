"""The upload lookup: what an upload of ``PUT .../rounds/{round}/models/{model_id}`` is checked
against (``crud.upload_targets``), read for every upload queued at once, and read ahead for
the patrons of every round this process publishes.

One thread (a ``server.grouping.GroupWorker``) reads every lookup queued since its last pass in
one transaction of six queries, so 64 agents uploading at once cost a few reads, not 64 thread
hops of four queries each.

Read ahead: when the round watcher sees a round open (``round_seen``), the targets of all its
asked patrons are read in one pass a moment later (``PRIME_DELAY_S``: after the round has
been pushed to the agents, while they fine-tune) and kept until the round closes, so the
uploads of an open round are checked without a database read. What such a target holds does
not change while its round is open: a participant's token, the version its patron bids with
(changed only when the round closes) and the round itself. What can change (the round
closing, the patron answering) the upload writer (in the screening process) checks again in
its own transaction, which alone decides whether an upload is in time and whether it is the
patron's first.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
from collections import OrderedDict
from collections.abc import Sequence

from agents.manifest import parse_manifest
from server import crud
from server.db import Database
from server.grouping import GroupWorker
from server.status import RoundStatus
from sim.market.design import Design, design

PRIME_DELAY_S = 0.01
"""How long after a round is seen open its targets are read ahead (the round's answers are
pushed to its agents first)."""
MAX_PRIMED = 64
"""Rounds whose targets are kept read ahead (the least recently primed go first)."""
MAX_DESIGNS = 4096
"""Designs of current versions kept (a version never changes)."""


def _raised(exc: Exception) -> BaseException:
    """A failed read is raised in every lookup of its batch."""
    return exc


class UploadLookup:
    """``await get(key)`` from any event loop; the reads happen on one thread, grouped."""

    def __init__(self, database: Database) -> None:
        self._database = database
        self._worker: GroupWorker[crud.UploadKey, crud.UploadTarget] = GroupWorker(
            "upload-lookup", self._read, on_error=_raised
        )
        self._primed: OrderedDict[tuple[int, int], dict[int, crud.UploadTarget]] = OrderedDict()
        """(auction id, round) → model id → target, for open rounds read ahead."""
        self._designs: OrderedDict[int, Design] = OrderedDict()
        """version id → its design (touched on the lookup thread only)."""
        self._open: OrderedDict[int, int] = OrderedDict()
        """auction id → the number of its round last seen open."""
        self.reads = 0
        """Passes that read the database so far (diagnostics and tests)."""

    def start(self) -> None:
        self._worker.start()

    def shutdown(self) -> None:
        self._worker.shutdown()

    async def get(self, key: crud.UploadKey) -> crud.UploadTarget:
        """The upload's target; raises ``crud.UploadLookupError`` (no such auction or model),
        SQLAlchemy's OperationalError (the database is unavailable) or
        ``server.grouping.StoppingError`` (the server is stopping)."""
        auction_id, model_id, number = key
        primed = self._primed.get((auction_id, number))
        if primed is not None and model_id in primed:
            return primed[model_id]
        return await self._worker.put(key)

    def round_seen(
        self, auction_id: int, number: int | None, status: str, asked: Sequence[int]
    ) -> None:
        """The round watcher read the auction's newest round (called on its event loop when
        what it read changed): an open round's targets are read ahead; a round no longer open
        is forgotten."""
        is_open = number is not None and status == RoundStatus.OPEN
        for key in [k for k in self._primed if k[0] == auction_id]:
            if not is_open or key[1] != number:
                del self._primed[key]
        if not is_open:
            self._open.pop(auction_id, None)
            return
        assert number is not None
        if self._open.get(auction_id) == number:
            return
        self._open[auction_id] = number
        while len(self._open) > MAX_PRIMED:
            self._open.popitem(last=False)
        keys = [(auction_id, model_id, number) for model_id in asked]
        loop = asyncio.get_running_loop()
        loop.call_later(PRIME_DELAY_S, lambda: asyncio.ensure_future(self._prime(keys)))

    async def _prime(self, keys: list[crud.UploadKey]) -> None:
        """Read the targets of ``keys`` (one round's patrons) and keep those of patrons who
        have not answered yet, if the round is still open by then."""
        auction_id, _, number = keys[0]
        try:
            found = await asyncio.gather(*(self._worker.put(key) for key in keys))
        except Exception:  # not read ahead: the uploads read their targets themselves
            return
        if self._open.get(auction_id) != number:
            return
        self._primed[auction_id, number] = {
            key[1]: target
            for key, target in zip(keys, found, strict=True)
            if target.round_status == RoundStatus.OPEN and target.answer_outcome is None
        }
        while len(self._primed) > MAX_PRIMED:
            self._primed.popitem(last=False)

    def answered(self, key: crud.UploadKey, body_sha256: str, answer: bytes) -> None:
        """An upload of ``key`` was answered (``answer``, the stored JSON bytes): its read-ahead
        target, if any, now holds that answer, so that this process checks the patron's next
        upload to the round as answered (a repeat gets the same bytes, another body 409)
        before its design; the writer still decides alone."""
        auction_id, model_id, number = key
        primed = self._primed.get((auction_id, number))
        if primed is None or model_id not in primed:
            return
        stored = json.loads(answer)
        primed[model_id] = dataclasses.replace(
            primed[model_id],
            answer_outcome=stored["outcome"],
            answer_sha256=body_sha256,
            answer=stored,
        )

    def primed(self, auction_id: int, number: int) -> bool:
        """Whether the targets of that open round are read ahead."""
        return (auction_id, number) in self._primed

    def _read(self, keys: list[crud.UploadKey]) -> Sequence[crud.UploadTarget | BaseException]:
        self.reads += 1
        with self._database.session(write=False) as session:
            found = crud.upload_targets(session, keys=keys)
        return [
            t
            if isinstance(t, BaseException)
            else dataclasses.replace(t, current_design=self._design(t))
            for t in found
        ]

    def _design(self, target: crud.UploadTarget) -> Design:
        """The design of the version the patron bids with (kept: versions never change)."""
        known = self._designs.get(target.current_id)
        if known is None:
            known = self._designs[target.current_id] = design(
                parse_manifest(target.current_manifest)
            )
            while len(self._designs) > MAX_DESIGNS:
                self._designs.popitem(last=False)
        return known
