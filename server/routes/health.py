"""Liveness and readiness: 200 while the database this server opened is there, else 503."""

from __future__ import annotations

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from server.deps import ComputeDep, DatabaseDep
from server.errors import api_error, responses
from server.schemas import HealthPublic

router = APIRouter(tags=["health"])


@router.get("/healthz", operation_id="healthz", responses=responses(503))
async def healthz(database: DatabaseDep, compute: ComputeDep) -> HealthPublic:
    """The server is up and its database is the one it started with (503 once that database
    is deleted, replaced or unreachable: writes are then refused too); which job backend
    computes the jobs' units, on how many CPUs."""
    problem = await run_in_threadpool(database.problem)
    if problem is not None:
        raise api_error(503, problem, loc=("database",), kind="db_unavailable")
    cpus = await run_in_threadpool(compute.cpus)
    return HealthPublic(status="ok", job_backend=compute.name, cpus=cpus)
