"""Readiness and liveness.

``GET /healthz`` is the readiness answer (the compose healthcheck and ``srd healthcheck`` ask
it): 200 when the server can take writes, 503 naming every problem (``server.api.readiness``).
``GET /livez`` is liveness: 200 while the process serves requests, whatever the database.
"""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from server.api.deps import ComputeDep, ReadinessDep, SettingsDep
from server.api.schemas import HealthProblem, HealthPublic, LivePublic
from server.services import screener_populations
from server.store.db import DATABASE_RETRY_AFTER_S

router = APIRouter(tags=["health"])


@router.get(
    "/healthz",
    operation_id="healthz",
    response_model=HealthPublic,
    responses={503: {"model": HealthPublic, "description": "Not ready: the problems found"}},
)
async def healthz(
    readiness: ReadinessDep, compute: ComputeDep, settings: SettingsDep
) -> HealthPublic | JSONResponse:
    """Ready (200) or not (503 with ``Retry-After``): the database is the one this server
    started with, reachable and writable; the data folder can be written; the disks of the
    data folder and of a SQLite database have ``SRD_MIN_FREE_DISK_MB`` free; the screener's
    process runs and answers (not holding requests 30 s unanswered). The answer is kept a
    second. Also which job backend computes the jobs' units, on how many CPUs, and
    which populations the screener's market-impact test meets."""
    problems = readiness.cached()
    if problems is None:
        problems = await run_in_threadpool(readiness.check)
    cpus = await run_in_threadpool(compute.cpus)
    health = HealthPublic(
        status="unavailable" if problems else "ok",
        problems=[HealthProblem(check=p.check, msg=p.msg) for p in problems],
        job_backend=compute.name,
        cpus=cpus,
        screener_populations=screener_populations(settings),
    )
    if not problems:
        return health
    return JSONResponse(
        health.model_dump(mode="json"),
        status_code=503,
        headers={"Retry-After": str(DATABASE_RETRY_AFTER_S)},
    )


@router.get("/livez", operation_id="livez")
async def livez() -> LivePublic:
    """Alive: the process serves requests (no check of the database or the disks)."""
    return LivePublic(status="ok")
