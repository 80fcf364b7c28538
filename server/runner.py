"""Background work: the one runner of auctions and jobs.

An auction and a job are both a database row played to its end by a task in a worker process
(``server.workers.WorkerPool``): ``server.auctions.AUCTION_WORK`` and
``server.jobs.worker.JOB_WORK``. ``BackgroundRunner`` runs the rows of one ``WorkKind``: it
queues them on its pool, resumes the unfinished ones at start, stops one on request, and
records on the row why a task ended without finishing it (its process died, or it hit the
time limit).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from sqlalchemy.orm import Session

from server import crud
from server.db import Database
from server.models import Auction, Job
from server.workers import TaskFn, WorkerContext, WorkerPool

log = logging.getLogger("srd.runner")


@dataclass(frozen=True)
class WorkKind:
    """What a runner plays: the rows of one table, each by one task."""

    name: str
    """``auction`` or ``job``: the pool's and the log's name."""
    table: type[Auction] | type[Job]
    task: TaskFn
    timeout_setting: str
    """The setting of the wall-time limit, as failures name it."""
    died: str
    """The error of a row whose worker died, formatted with its exit ``code``."""
    resumable: Callable[[Session], list[int]]
    """The rows to play again at start, oldest first (their state made ready for it)."""
    tasks_per_process: int | None = None
    """Tasks one worker process runs before it is replaced (None: no limit)."""


class BackgroundRunner:
    """Plays the rows of one ``WorkKind`` on a pool of ``max_workers`` worker processes, each
    task stopped after ``timeout_s``."""

    def __init__(
        self,
        database: Database,
        context: WorkerContext,
        kind: WorkKind,
        *,
        max_workers: int,
        timeout_s: float,
    ) -> None:
        self._database = database
        self.kind = kind
        self.pool = WorkerPool(
            name=kind.name,
            task=kind.task,
            context=context,
            max_workers=max_workers,
            on_exit=self._on_exit,
            tasks_per_process=kind.tasks_per_process,
            timeout_s=timeout_s,
            on_timeout=self._on_timeout,
        )

    def start(self) -> None:
        """Start the pool and queue every row left unfinished."""
        self.pool.start()
        with self._database.session(write=True) as session:
            resumed = self.kind.resumable(session)
            session.commit()
        for row_id in resumed:
            log.info("resuming %s %d", self.kind.name, row_id)
            self.pool.submit(row_id)

    def submit(self, row_id: int) -> None:
        """Play a new row as soon as a worker is free."""
        self.pool.submit(row_id)

    def cancel(self, row_id: int) -> None:
        """Stop a row wherever it is (queued or running); its row already says why."""
        self.pool.cancel(row_id)

    def shutdown(self) -> None:
        """Stop the workers; their rows resume at the next start."""
        self.pool.shutdown()

    def _on_exit(self, row_id: int, exit_code: int | None) -> None:
        """The worker process died in the middle of this row (killed, crashed)."""
        self._fail(row_id, self.kind.died.format(code=exit_code))

    def _on_timeout(self, row_id: int, limit_s: float) -> None:
        name, setting = self.kind.name, self.kind.timeout_setting
        self._fail(row_id, f"stopped at the {name} time limit of {limit_s:g} s ({setting})")

    def _fail(self, row_id: int, error: str) -> None:
        with self._database.session(write=True) as session:
            crud.fail_unfinished(session, table=self.kind.table, row_id=row_id, error=error)
            session.commit()
