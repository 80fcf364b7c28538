"""Jobs: run the paper's experiments in the background (``POST``/``DELETE`` are operator-only)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse
from starlette.concurrency import run_in_threadpool

from server import crud
from server.config import Settings
from server.db import SessionDep
from server.errors import api_error, error_item, link, responses, validation_error
from server.jobs import JobBackend
from server.jobs.worker import job_dir
from server.models import Job
from server.pages import DEFAULT_PAGE, PageCursor, PageLimit, page_of
from server.schemas import JobCreate, JobCreated, JobIdPath, JobPage, JobPublic, JobSummaryPublic
from server.security import AdminDep
from sim.experiment import ConfigError, config_dict, over_budget
from sim.registry import build_config

router = APIRouter(tags=["jobs"])

ARTIFACT_TYPES = ("image/png", "image/gif", "text/csv", "application/json", "text/plain")


def _job_public(job: Job) -> JobPublic:
    return JobPublic(
        id=job.id,
        kind=job.kind,
        status=job.status,
        progress=job.progress,
        message=job.message,
        params=job.params,
        result=job.result,
        error=job.error,
        artifacts=job.artifacts,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
    )


def _path(field: str) -> list[str | int]:
    """A config error's dotted field (``rarities.1``) as a ``loc`` tail."""
    return [int(part) if part.isdigit() else part for part in field.split(".")]


def _existing_job(session: SessionDep, job_id: int) -> Job:
    job = crud.get_job(session, job_id=job_id)
    if job is None:
        raise api_error(
            404, f"job {job_id} does not exist", loc=("path", "job_id"), kind="not_found"
        )
    return job


@router.post(
    "/jobs",
    status_code=202,
    dependencies=[AdminDep],
    operation_id="create_job",
    responses={
        202: {
            "links": {
                "ReadJob": link("read_job", "job_id", "job_id"),
                "CancelJob": link("cancel_job", "job_id", "job_id"),
            }
        },
        **responses(401, 403, 422),
    },
)
def create_job(body: JobCreate, session: SessionDep, request: Request) -> JobCreated:
    """Queue an experiment (operator); ``params`` are the CLI options of ``kind``. A job whose
    estimated compute exceeds the budget (``SRD_JOB_BUDGET_S``) is refused, naming the option
    to lower and how far."""
    settings: Settings = request.app.state.settings
    try:
        config = build_config(body.kind, body.params)
        too_much = over_budget(config, settings.job_budget_s)
        if too_much is not None:
            raise too_much
    except ConfigError as exc:
        raise validation_error(
            error_item(
                err["message"], loc=("body", "params", *_path(err["field"])), kind="bad_param"
            )
            for err in exc.errors
        ) from exc
    job = crud.create_job(session, kind=body.kind, params=config_dict(config))
    session.commit()
    backend: JobBackend = request.app.state.jobs
    backend.submit(job.id)
    return JobCreated(job_id=job.id, status="queued")


@router.get("/jobs/{job_id}", operation_id="read_job", responses=responses(404, 422))
def read_job(job_id: JobIdPath, session: SessionDep) -> JobPublic:
    """A job's status, progress, result (the CLI's ``--json`` object), error and artifacts."""
    return _job_public(_existing_job(session, job_id))


@router.get(
    "/jobs/{job_id}/artifacts/{name:path}",
    response_class=FileResponse,
    operation_id="read_artifact",
    responses={
        200: {"description": "The artifact file", "content": {t: {} for t in ARTIFACT_TYPES}},
        **responses(404, 422),
    },
)
def read_artifact(
    job_id: JobIdPath, name: str, session: SessionDep, request: Request
) -> FileResponse:
    """One artifact file of a job (a name listed in its ``artifacts``)."""
    job = _existing_job(session, job_id)
    missing = api_error(
        404, f"job {job_id} has no artifact {name!r}", loc=("path", "name"), kind="not_found"
    )
    if name not in job.artifacts:  # before touching the file system with the name
        raise missing
    base = job_dir(request.app.state.settings.data_dir, job_id).resolve()
    path = (base / name).resolve()
    if not path.is_relative_to(base) or not path.is_file():
        raise missing
    return FileResponse(path, filename=Path(name).name, content_disposition_type="inline")


@router.delete(
    "/jobs/{job_id}",
    dependencies=[AdminDep],
    operation_id="cancel_job",
    responses=responses(401, 403, 404, 409, 422),
)
def cancel_job(job_id: JobIdPath, session: SessionDep, request: Request) -> JobPublic:
    """Cancel a queued or running job (operator); a running job's process is terminated."""
    job = _existing_job(session, job_id)
    if not crud.cancel_job(session, job_id=job_id):
        raise api_error(
            409,
            f"job {job_id} already {job.status}; only queued or running jobs can be cancelled",
            loc=("path", "job_id"),
            kind="not_cancellable",
        )
    session.commit()
    backend: JobBackend = request.app.state.jobs
    backend.cancel(job_id)
    session.refresh(job)
    return _job_public(job)


@router.get("/jobs", operation_id="list_jobs", responses=responses(422))
async def list_jobs(
    session: SessionDep, limit: PageLimit = DEFAULT_PAGE, cursor: PageCursor = None
) -> JobPage:
    """Jobs with their status and progress, newest first, a page at a time."""
    rows = await run_in_threadpool(crud.list_jobs, session, before=cursor, limit=limit + 1)
    items, next_cursor = page_of(rows, limit)
    return JobPage(
        items=[JobSummaryPublic(**dataclasses.asdict(row)) for row in items],
        next_cursor=next_cursor,
    )
