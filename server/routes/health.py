"""Liveness and readiness: 200 while the database this server opened is there, else 503."""

from __future__ import annotations

from fastapi import APIRouter, Request
from starlette.concurrency import run_in_threadpool

from server.db import Database
from server.errors import api_error, responses
from server.jobs.backend import JobCompute
from server.schemas import HealthPublic

router = APIRouter(tags=["health"])


@router.get("/healthz", operation_id="healthz", responses=responses(503))
async def healthz(request: Request) -> HealthPublic:
    """The server is up and its database is the one it started with (503 once that database
    is deleted, replaced or unreachable: writes are then refused too); which job backend
    computes the jobs' units, on how many CPUs."""
    database: Database = request.app.state.database
    problem = await run_in_threadpool(database.problem)
    if problem is not None:
        raise api_error(503, problem, loc=("database",), kind="db_unavailable")
    compute: JobCompute = request.app.state.compute
    cpus = await run_in_threadpool(compute.cpus)
    return HealthPublic(status="ok", job_backend=compute.name, cpus=cpus)
