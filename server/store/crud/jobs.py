"""Jobs: creating, reading, cancelling and listing them; and failing an unfinished auction or
job (how the background runner gives up on either)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from server.store.crud.auctions import close_open_rounds
from server.store.crud.lists import ListOrder, keyset
from server.store.crud.live import notify_change, notify_due
from server.store.status import AUCTION_UNFINISHED, JOB_UNFINISHED, AuctionStatus, JobStatus
from server.store.tables import Auction, Job, utcnow


def create_job(session: Session, *, kind: str, params: dict[str, Any]) -> Job:
    """A queued job."""
    now = utcnow()
    job = Job(
        kind=kind,
        params=params,
        status=JobStatus.QUEUED,
        progress=0.0,
        message="queued",
        artifacts=[],
        attempt=0,
        created_at=now,
        updated_at=now,
    )
    session.add(job)
    session.flush()
    notify_due(session, kind="job")
    return job


def count_queued(session: Session) -> int:
    """Jobs waiting to run."""
    queued = select(func.count()).select_from(Job).where(Job.status == JobStatus.QUEUED)
    return session.scalar(queued) or 0


def get_job(session: Session, *, job_id: int) -> Job | None:
    """A job by id."""
    return session.get(Job, job_id)


def fail_unfinished(
    session: Session, *, table: type[Auction] | type[Job], row_id: int, error: str
) -> None:
    """Mark an auction or job failed with ``error``, unless it has already ended; a failed
    auction's open fine-tuning round is closed with it, as a cancelled one's."""
    unfinished, failed = (
        (AUCTION_UNFINISHED, AuctionStatus.FAILED)
        if table is Auction
        else (JOB_UNFINISHED, JobStatus.FAILED)
    )
    now = utcnow()
    values: dict[str, Any] = {"status": failed, "error": error, "finished_at": now}
    if table is Job:  # the cause in the message too: a view showing only it says why
        values["message"] = f"failed: {error.splitlines()[0] if error else 'unknown'}"[:200]
    if table is Auction:  # before and after the row, as ``cancel_auction`` does
        close_open_rounds(session, row_id, now)
    failed_now = session.execute(
        update(table)
        .where(table.id == row_id, table.status.in_(unfinished))
        .values(updated_at=now, **values)
    )
    if failed_now.rowcount:  # type: ignore[attr-defined]
        if table is Auction:
            close_open_rounds(session, row_id, now)
        notify_change(session, kind="auction" if table is Auction else "job", row_id=row_id)


def cancel_job(session: Session, *, job_id: int) -> bool:
    """Mark a queued or running job cancelled; False when it had already ended."""
    now = utcnow()
    changed = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.status.in_(JOB_UNFINISHED))
        .values(status=JobStatus.CANCELLED, message="cancelled", finished_at=now, updated_at=now)
    )
    if not changed.rowcount:  # type: ignore[attr-defined]
        return False
    notify_change(session, kind="job", row_id=job_id)
    return True


@dataclass(frozen=True)
class JobSummary:
    """A job as a list shows it (no result, no error text: those are on the job itself)."""

    id: int
    kind: str
    status: str
    progress: float
    message: str
    params: dict[str, Any]
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


_JOB_SUMMARY = select(*(getattr(Job, f.name) for f in dataclasses.fields(JobSummary))).order_by(
    Job.id.desc()
)


def list_jobs(
    session: Session,
    *,
    before: int | None,
    limit: int,
    status: str | None = None,
    kind: str | None = None,
    order: ListOrder = "newest",
) -> list[JobSummary]:
    """Up to ``limit`` jobs after the cursor ``before`` in ``order``, of ``status`` and ``kind``
    if given (one query)."""
    query = keyset(_JOB_SUMMARY, Job.id, cursor=before, order=order).limit(limit)
    if status is not None:
        query = query.where(Job.status == status)
    if kind is not None:
        query = query.where(Job.kind == kind)
    return [JobSummary(*row) for row in session.connection().execute(query)]


class SupersededError(Exception):
    """The job is no longer this attempt's to write: cancelled, or claimed again as a new
    attempt."""


def update_attempt(session: Session, *, job_id: int, attempt: int, values: dict[str, Any]) -> None:
    """Write ``values`` to a running job if ``attempt`` is still its attempt (SupersededError
    otherwise), and announce it."""
    changed = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.attempt == attempt, Job.status == JobStatus.RUNNING)
        .values(updated_at=utcnow(), **values)
    )
    if changed.rowcount != 1:  # type: ignore[attr-defined]
        raise SupersededError
    notify_change(session, kind="job", row_id=job_id)


def start_job(session: Session, *, job_id: int) -> tuple[str, dict[str, Any], int] | None:
    """A queued job made running as its next attempt: its kind, params and attempt (None: it
    is not queued any more)."""
    now = utcnow()
    started = session.execute(
        update(Job)  # one conditional statement: a cancel committed since is never undone
        .where(Job.id == job_id, Job.status == JobStatus.QUEUED)
        .values(status=JobStatus.RUNNING, attempt=Job.attempt + 1, started_at=now,
                updated_at=now, progress=0.0, message="started", error=None, result=None)
        .returning(Job.kind, Job.params, Job.attempt)
        .execution_options(synchronize_session=False)
    ).one_or_none()  # fmt: skip
    if started is None:
        return None
    notify_change(session, kind="job", row_id=job_id)
    kind, params, attempt = started
    return kind, dict(params), attempt


def requeue_jobs(session: Session, *, job_ids: list[int], message: str) -> None:
    """Running jobs among ``job_ids`` back to queued, with ``message``."""
    session.execute(
        update(Job)
        .where(Job.id.in_(job_ids), Job.status == JobStatus.RUNNING)
        .values(
            status=JobStatus.QUEUED,
            progress=0.0,
            message=message,
            started_at=None,
            updated_at=utcnow(),
        )
    )
    for job_id in job_ids:
        notify_change(session, kind="job", row_id=job_id)
