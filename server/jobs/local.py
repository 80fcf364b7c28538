"""The default job backend: each job in its own spawned process on this machine."""

from __future__ import annotations

from server import crud
from server.db import Database
from server.jobs.backend import JobBackend
from server.jobs.worker import run_job
from server.models import Job
from server.workers import WorkerContext, WorkerPool


class LocalJobBackend(JobBackend):
    """Spawned worker processes, ``max_workers`` jobs at a time, in submission order."""

    def __init__(
        self,
        database: Database,
        context: WorkerContext,
        *,
        max_workers: int,
        timeout_s: float,
    ) -> None:
        self._database = database
        self.pool = WorkerPool(
            name="job",
            task=run_job,
            context=context,
            max_workers=max_workers,
            on_exit=self._on_exit,
            tasks_per_process=1,  # a fresh interpreter per experiment: no state carried over
            timeout_s=timeout_s,
            on_timeout=self._on_timeout,
        )

    def start(self) -> None:
        self.pool.start()

    def submit(self, job_id: int) -> None:
        self.pool.submit(job_id)

    def cancel(self, job_id: int) -> None:
        self.pool.cancel(job_id)

    def shutdown(self) -> None:
        self.pool.shutdown()

    def _on_exit(self, job_id: int, exit_code: int | None) -> None:
        """The worker process died in the middle of this job (killed, crashed)."""
        self._fail(job_id, f"the job worker exited (code {exit_code}) without a result")

    def _on_timeout(self, job_id: int, limit_s: float) -> None:
        self._fail(job_id, f"stopped at the job time limit of {limit_s:g} s (SRD_JOB_TIMEOUT_S)")

    def _fail(self, job_id: int, error: str) -> None:
        with self._database.session(write=True) as session:
            crud.fail_unfinished(session, table=Job, row_id=job_id, error=error)
            session.commit()
