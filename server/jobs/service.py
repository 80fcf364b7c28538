"""Jobs: queue an experiment within the compute budget (operator), read one, cancel one, find
one of its artifact files."""

from __future__ import annotations

import logging
from collections import OrderedDict
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from server.api.errors import RequestError, api_error, error_item, validation_error
from server.api.readiness import DATA_FOLDER, disk_problem_kind
from server.jobs.worker import job_dir
from server.store import crud
from server.store.tables import Job
from server.work.runner import BackgroundRunner
from sim.experiment import ConfigError, config_dict, over_budget
from studies.registry import build_config

JOB_QUEUE_RETRY_AFTER_S = 30
"""``Retry-After`` of a job refused because the queue is full."""

log = logging.getLogger("srd.jobs")

ENDED_JOBS_BYTES = 64 << 20
"""At most this much ended jobs' JSON is kept in each API process (``EndedJobs``)."""


def _path(field: str) -> list[str | int]:
    """A config error's dotted field (``rarities.1``) as a ``loc`` tail."""
    return [int(part) if part.isdigit() else part for part in field.split(".") if part]


def create_job(
    session: Session,
    runner: BackgroundRunner,
    *,
    kind: str,
    params: dict[str, Any],
    budget_s: float,
    max_queued: int,
    data_dir: Path,
    min_free_disk_mb: int,
) -> Job:
    """Validate ``params`` by the kind's config, refuse a job over ``budget_s`` of estimated
    compute (naming the option to lower and how far), one past ``max_queued`` waiting jobs or
    one whose artifacts would go to a disk with less than ``min_free_disk_mb`` free, store it
    queued, hand it to the runner."""
    try:
        config = build_config(kind, params)
        too_much = over_budget(config, budget_s)
        if too_much is not None:
            raise too_much
    except ConfigError as exc:
        raise validation_error(
            error_item(
                err["message"], loc=("body", "params", *_path(err["field"])), kind="bad_param"
            )
            for err in exc.errors
        ) from exc
    if min_free_disk_mb > 0:  # its artifacts would fill what is left
        found = disk_problem_kind(data_dir, min_free_disk_mb, DATA_FOLDER)
        if found is not None:
            kind_of_problem, full = found
            raise api_error(
                503,
                f"{full}: no job is queued until there is room for its artifacts",
                loc=("server",),
                kind=kind_of_problem,
                headers={"Retry-After": str(JOB_QUEUE_RETRY_AFTER_S)},
            )
    crud.lock_subject(session, "queued-jobs")  # concurrent creations count one another
    queued = crud.count_queued(session)
    if queued >= max_queued:
        raise api_error(
            503,
            f"{queued} jobs are waiting to run, the most this server queues "
            f"(SRD_MAX_QUEUED_JOBS); retry once some have started",
            loc=("server",),
            kind="too_many_jobs",
            headers={"Retry-After": str(JOB_QUEUE_RETRY_AFTER_S)},
        )
    job = crud.create_job(session, kind=kind, params=config_dict(config))
    session.commit()
    runner.submit(job.id)
    return job


def _not_found(job_id: int) -> RequestError:
    return api_error(404, f"job {job_id} does not exist", loc=("path", "job_id"), kind="not_found")


def read_job(session: Session, job_id: int) -> Job:
    """A job (404 if there is none)."""
    job = crud.get_job(session, job_id=job_id)
    if job is None:
        raise _not_found(job_id)
    return job


def require_job(session: Session, job_id: int) -> crud.JobState:
    """Where a job stands (404 if there is none)."""
    state = crud.job_state(session, job_id=job_id)
    if state is None:
        raise _not_found(job_id)
    return state


def cancel_job(session: Session, runner: BackgroundRunner, job_id: int) -> Job:
    """Cancel a queued or running job (409 once it has ended) and stop its worker."""
    job = read_job(session, job_id)
    if not crud.cancel_job(session, job_id=job_id):
        session.rollback()  # expires the job: the message names the status that ended it
        raise api_error(
            409,
            f"job {job_id} already {job.status}; only queued or running jobs can be cancelled",
            loc=("path", "job_id"),
            kind="not_cancellable",
        )
    session.commit()
    log.info("job %d cancelled", job_id)
    runner.cancel(job_id)
    session.refresh(job)
    return job


def artifact_path(session: Session, data_dir: Path, job_id: int, name: str) -> Path:
    """The file of one artifact a job lists (404 otherwise); the name is checked against the
    job's list before it touches the file system."""
    job = read_job(session, job_id)
    shown = name if len(name) <= 64 else f"{name[:64]}…"  # a name of 5,000 characters
    missing = api_error(
        404, f"job {job_id} has no artifact {shown!r}", loc=("path", "name"), kind="not_found"
    )
    if name not in job.artifacts:
        raise missing
    base = job_dir(data_dir, job_id).resolve()
    path = (base / name).resolve()
    if not path.is_relative_to(base) or not path.is_file():
        raise missing
    return path


class EndedJobs:
    """The JSON of ended jobs, which never change again, as ``GET /jobs/{id}`` sends it: a
    result can be a megabyte (a cheetah grid lists every run), which took 20 ms of the event
    loop to read, check and encode on every request. Kept least recently read first out, at
    most ``max_bytes`` in all; a body larger than that is not kept. Used on the event loop
    only (no lock)."""

    def __init__(self, max_bytes: int) -> None:
        self._max_bytes = max_bytes
        self._bodies: OrderedDict[int, bytes] = OrderedDict()
        self._bytes = 0

    def get(self, job_id: int) -> bytes | None:
        body = self._bodies.get(job_id)
        if body is not None:
            self._bodies.move_to_end(job_id)
        return body

    def put(self, job_id: int, body: bytes) -> None:
        if len(body) > self._max_bytes:
            return
        old = self._bodies.pop(job_id, None)
        self._bytes += len(body) - (0 if old is None else len(old))
        self._bodies[job_id] = body
        while self._bytes > self._max_bytes:
            _, dropped = self._bodies.popitem(last=False)
            self._bytes -= len(dropped)
