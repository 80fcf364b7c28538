"""The job backend interface: where and how queued jobs get executed.

The database row is the source of truth (status, progress, result, error, artifacts); a backend
only runs ``server.jobs.worker.run_job`` for a job id somewhere and can stop it. The default is
``LocalJobBackend`` (spawned processes on this machine); a cluster backend would implement the
same four methods.
"""

from __future__ import annotations

import os
from abc import ABC, abstractmethod
from typing import Protocol

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from server.config import JobBackendName
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


class JobCompute(Protocol):
    """Where job units are computed, as ``/healthz`` reports it."""

    name: JobBackendName

    def cpus(self) -> float:
        """The CPUs the backend can compute units on."""

    def close(self) -> None:
        """Let go of the backend (at shutdown)."""


class LocalCompute:
    """Units computed by the job worker processes of this machine."""

    name: JobBackendName = "local"

    def cpus(self) -> float:
        """The CPUs this process may run on."""
        return float(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1)

    def close(self) -> None:
        """Nothing to let go of."""


def job_compute(backend: JobBackendName, ray_address: str | None) -> JobCompute:
    """The compute of ``SRD_JOB_BACKEND``: joins the Ray cluster for ``ray`` (raising
    ``RayUnavailableError`` with the reason when Ray is missing or unreachable)."""
    if backend != "ray":
        return LocalCompute()
    from server.jobs.ray_backend import RayCluster

    return RayCluster(ray_address)


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
