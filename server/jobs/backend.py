"""The job backend interface: where and how queued jobs get executed.

The database row is the source of truth (status, progress, result, error, artifacts); a backend
only runs ``server.jobs.worker.run_job`` for a job id somewhere and can stop it. The default is
``LocalJobBackend`` (spawned processes on this machine); a cluster backend would implement the
same four methods.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from server.models import Job, utcnow


class JobBackend(ABC):
    """Runs jobs by id; never blocks the caller."""

    @abstractmethod
    def start(self) -> None:
        """Begin accepting work."""

    @abstractmethod
    def submit(self, job_id: int) -> None:
        """Run a queued job as soon as capacity allows."""

    @abstractmethod
    def cancel(self, job_id: int) -> None:
        """Stop a job wherever it is (queued or running); its row is already 'cancelled'."""

    @abstractmethod
    def shutdown(self) -> None:
        """Stop running jobs; they are re-queued at the next start."""


def requeue_unfinished(session: Session) -> list[int]:
    """At start-up: jobs left running go back to queued; returns every queued id, oldest first."""
    session.execute(
        update(Job)
        .where(Job.status == "running")
        .values(
            status="queued",
            progress=0.0,
            message="re-queued after a server restart",
            started_at=None,
            updated_at=utcnow(),
        )
    )
    queued = list(session.scalars(select(Job.id).where(Job.status == "queued").order_by(Job.id)))
    session.commit()
    return queued
