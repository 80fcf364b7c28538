"""Jobs: run the paper's experiments in the background (``POST``/``DELETE`` are operator-only)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Query, Response
from fastapi.responses import FileResponse

from server.api.deps import (
    AdminDep,
    EndedJobsDep,
    JobRunnerDep,
    NoBodyDep,
    SessionDep,
    SettingsDep,
    read_in_thread,
)
from server.api.errors import link, responses
from server.api.files import ServedFile
from server.api.pages import DEFAULT_PAGE, PageCursor, PageLimit, PageOrder, page_of
from server.api.schemas import (
    JobCreate,
    JobCreated,
    JobIdPath,
    JobKind,
    JobPage,
    JobPublic,
    JobSummaryPublic,
)
from server.jobs import service as jobs
from server.store import crud
from server.store.status import JOB_ENDED, JobStatus
from server.store.tables import Job

router = APIRouter(tags=["jobs"])

ARTIFACT_TYPES = ("image/png", "image/gif", "text/csv", "application/json", "text/plain")


def _job_public(job: Job) -> JobPublic:
    return JobPublic.model_validate(job, from_attributes=True)


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
        **responses(401, 403, 422, 503),
    },
)
def create_job(
    body: JobCreate, session: SessionDep, runner: JobRunnerDep, settings: SettingsDep
) -> JobCreated:
    """Queue an experiment (operator); ``params`` are the CLI options of ``kind``. A job whose
    estimated compute exceeds the budget (``SRD_JOB_BUDGET_S``) is refused, naming the option
    to lower and how far; past ``SRD_MAX_QUEUED_JOBS`` waiting jobs, or with less than
    ``SRD_MIN_FREE_DISK_MB`` free for its artifacts, 503 with ``Retry-After``."""
    job = jobs.create_job(
        session,
        runner,
        kind=body.kind,
        params=body.params,
        budget_s=settings.job_budget_s,
        max_queued=settings.max_queued_jobs,
        data_dir=settings.data_dir,
        min_free_disk_mb=settings.min_free_disk_mb,
    )
    return JobCreated(job_id=job.id, status=JobStatus.QUEUED)


@router.get(
    "/jobs/{job_id}",
    response_model=JobPublic,
    operation_id="read_job",
    responses=responses(404, 422),
)
async def read_job(job_id: JobIdPath, session: SessionDep, ended: EndedJobsDep) -> Response:
    """A job's status, progress, result (the CLI's ``--json`` object), error and artifacts."""
    body = ended.get(job_id)
    if body is None:
        job = _job_public(await read_in_thread(jobs.read_job, session, job_id))
        body = job.model_dump_json().encode()
        if job.status in JOB_ENDED:  # it never changes again
            ended.put(job_id, body)
    return Response(body, media_type="application/json")


@router.get(
    "/jobs/{job_id}/artifacts/{name:path}",
    response_class=FileResponse,
    operation_id="read_artifact",
    responses={
        200: {"description": "The artifact file", "content": {t: {} for t in ARTIFACT_TYPES}},
        206: {
            "description": "The part of the artifact file its Range asks for",
            "content": {t: {} for t in ARTIFACT_TYPES},
        },
        304: {"description": "Not modified: If-None-Match names the file's ETag"},
        **responses(404, 412, 416, 422),
    },
)
def read_artifact(
    job_id: JobIdPath, name: str, session: SessionDep, settings: SettingsDep
) -> FileResponse:
    """One artifact file of a job (a name listed in its ``artifacts``); a ``Range`` of it
    too (206; one it cannot serve: 416 in JSON; a malformed one is ignored), and its
    preconditions evaluated (``If-None-Match``: 304; ``If-Match``: 412)."""
    path = jobs.artifact_path(session, settings.data_dir, job_id, name)
    return ServedFile(path, filename=Path(name).name, content_disposition_type="inline")


@router.delete(
    "/jobs/{job_id}",
    dependencies=[AdminDep, NoBodyDep],
    operation_id="cancel_job",
    responses=responses(401, 403, 404, 409, 422),
)
def cancel_job(job_id: JobIdPath, session: SessionDep, runner: JobRunnerDep) -> JobPublic:
    """Cancel a queued or running job (operator); a running job's process is terminated."""
    return _job_public(jobs.cancel_job(session, runner, job_id))


@router.get("/jobs", operation_id="list_jobs", responses=responses(422))
async def list_jobs(
    session: SessionDep,
    limit: PageLimit = DEFAULT_PAGE,
    cursor: PageCursor = None,
    status: Annotated[JobStatus | None, Query(description="Only jobs in this status.")] = None,
    kind: Annotated[JobKind | None, Query(description="Only jobs of this kind.")] = None,
    order: PageOrder = "newest",
) -> JobPage:
    """Jobs with their status and progress, newest (or oldest) first, a page at a time."""
    rows = await read_in_thread(
        crud.list_jobs,
        session,
        before=cursor,
        limit=limit + 1,
        status=status,
        kind=kind,
        order=order,
    )
    items, next_cursor = page_of(rows, limit)
    return JobPage(
        items=[JobSummaryPublic(**dataclasses.asdict(row)) for row in items],
        next_cursor=next_cursor,
    )
