"""The upload lookup: what an upload of ``PUT .../rounds/{round}/models/{model_id}`` is checked
against (``crud.upload_targets``), read for every upload queued at once.

One thread (a ``server.grouping.GroupWorker``) reads every lookup queued since its last pass in
one transaction of six queries, so 64 agents uploading at once cost a few reads, not 64 thread
hops of four queries each.
"""

from __future__ import annotations

from collections.abc import Sequence

from server import crud
from server.db import Database
from server.grouping import GroupWorker


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

    def start(self) -> None:
        self._worker.start()

    def shutdown(self) -> None:
        self._worker.shutdown()

    async def get(self, key: crud.UploadKey) -> crud.UploadTarget:
        """The upload's target; raises ``crud.UploadLookupError`` (no such auction or model),
        SQLAlchemy's OperationalError (the database is unavailable) or
        ``server.grouping.StoppingError`` (the server is stopping)."""
        return await self._worker.put(key)

    def _read(self, keys: list[crud.UploadKey]) -> Sequence[crud.UploadTarget | BaseException]:
        with self._database.session(write=False) as session:
            return crud.upload_targets(session, keys=keys)
