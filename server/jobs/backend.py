"""The job backend: where a job's units are computed (``SRD_JOB_BACKEND``).

Every job runs in a worker process of the API's machine (``server.jobs.worker``); the backend
decides only where that worker computes the experiment's units: itself (``local``), or as
tasks on a Ray cluster (``ray``, ``server.jobs.ray_backend``). ``/healthz`` reports it.
"""

from __future__ import annotations

from typing import Protocol

from server.config import JobBackendName
from server.work.pool import usable_cpus


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
        return float(usable_cpus())

    def close(self) -> None:
        """Nothing to let go of."""


def job_compute(
    backend: JobBackendName, ray_address: str | None, ray_join_timeout_s: float
) -> JobCompute:
    """The compute of ``SRD_JOB_BACKEND``: for ``ray``, a look at the cluster (raising
    ``RayUnavailableError`` with the reason when Ray is missing or unreachable)."""
    if backend != "ray":
        return LocalCompute()
    from server.jobs.ray_backend import RayCluster

    return RayCluster(ray_address, ray_join_timeout_s)
