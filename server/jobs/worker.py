"""The job worker process: claim a queued job, run its experiment, record the outcome.

The experiment's units (``sim.units``) are computed here, or as Ray tasks with the ``ray``
backend (``server.jobs.ray_backend``); the artifacts and the result are made here either way.

Every write carries the attempt number taken at claim time and the 'running' status, so a
cancelled job or one re-claimed after a restart is never overwritten by an older worker.
"""

from __future__ import annotations

import logging
import math
import re
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from server.api.readiness import DATA_FOLDER, disk_problem_kind
from server.store import crud
from server.store.db import (
    OUTAGE_RETRIES,
    OUTAGE_WAIT_S,
    Database,
    is_database_outage,
    unavailable_message,
)
from server.store.status import JOB_UNFINISHED, JobStatus
from server.store.tables import Job, utcnow
from server.work.pool import WorkerContext, error_summary
from server.work.runner import WorkKind
from sim.experiment import json_safe, write_json
from sim.units import UnitRunner
from studies.registry import build_config, run_kind

log = logging.getLogger("srd.jobs")

MESSAGE_LIMIT = 200  # characters of a progress message kept


def job_dir(data_dir: str | Path, job_id: int) -> Path:
    """Where a job's artifacts live: ``<data_dir>/jobs/<id>/``."""
    return Path(data_dir) / "jobs" / str(job_id)


def list_artifacts(out_dir: Path) -> list[str]:
    """Every file under ``out_dir``, as sorted relative POSIX paths."""
    if not out_dir.is_dir():
        return []
    return sorted(p.relative_to(out_dir).as_posix() for p in out_dir.rglob("*") if p.is_file())


MB = 1 << 20


class JobDiskError(RuntimeError):
    """A job's files took more disk than ``SRD_JOB_DISK_MB``, or its disk was full when it was
    to start."""


def check_disk(out_dir: Path, context: WorkerContext) -> None:
    """Raise ``JobDiskError`` when the job's folder takes more than its ``job_disk_mb``."""
    if context.job_disk_mb is None or not out_dir.is_dir():
        return
    used = sum(p.stat().st_size for p in out_dir.rglob("*") if p.is_file())
    if used > context.job_disk_mb * MB:
        raise JobDiskError(
            f"its files take {used:,} bytes ({used / MB:.2f} MB), more than the "
            f"{context.job_disk_mb:.12g} MB a job may write (SRD_JOB_DISK_MB)"
        )


def check_free_disk(data_dir: Path, context: WorkerContext) -> None:
    """Raise ``JobDiskError`` when the data folder's disk has less than ``min_free_disk_mb``
    free: a job queued while there was room does not start on a full disk."""
    if context.min_free_disk_mb <= 0:
        return
    found = disk_problem_kind(data_dir, context.min_free_disk_mb, DATA_FOLDER)
    if found is not None:
        raise JobDiskError(f"{found[1]}: not started")


def _phase(message: str) -> str:
    """A progress message with its numbers blanked: ``step 102/3600`` and ``step 3600/3600``
    are one phase, ``drawing the figures`` another."""
    return _NUMBER.sub("#", message)


_NUMBER = re.compile(r"[-+]?[\d.]+(?:e[-+]?\d+)?")


class _Progress:
    """Throttled progress writes: at most one every ``interval_s`` seconds, besides the first
    report of each phase (its message, numbers aside, differs from the report before: the
    artifacts, the figures, the GIF after the steps) and the last (fraction 1). A phase that
    reports nothing for seconds then shows its own message, not the last step written."""

    def __init__(
        self,
        database: Database,
        job_id: int,
        attempt: int,
        interval_s: float,
        check: Callable[[], None] = lambda: None,
    ) -> None:
        self._check = check
        self._database = database
        self._job_id = job_id
        self._attempt = attempt
        self._interval_s = interval_s
        self._last = -math.inf
        self._phase: str | None = None

    def __call__(self, fraction: float, message: str) -> None:
        now = time.monotonic()
        phase, self._phase = self._phase, _phase(message)
        if not math.isfinite(fraction):
            return
        if now - self._last < self._interval_s and fraction < 1 and self._phase == phase:
            return
        self._last = now
        self._check()  # raises to stop the run (its files past their bound)
        try:
            _update_owned(
                self._database,
                self._job_id,
                self._attempt,
                progress=min(max(fraction, 0.0), 1.0),
                message=message[:MESSAGE_LIMIT],
            )
        except Exception as exc:  # the job goes on; the next report writes progress again
            if not is_database_outage(exc):
                raise
            log.warning("job %d: progress not written: %s", self._job_id, unavailable_message(exc))


def _update_owned(database: Database, job_id: int, attempt: int, **values: Any) -> None:
    with database.session(write=True) as session:
        crud.update_attempt(session, job_id=job_id, attempt=attempt, values=values)
        session.commit()


def _record_outcome(database: Database, job_id: int, attempt: int, **values: Any) -> None:
    """The job's last write, retried when the database comes back from an outage, however long
    it lasts (the job's time limit bounds the wait: its runner ends the worker then). Its result
    would be lost otherwise, and the job run again: after a 100 s outage it had been."""
    for retry in range(OUTAGE_RETRIES + 1):
        try:
            _update_owned(database, job_id, attempt, **values)
            return
        except Exception as exc:
            if not (is_database_outage(exc) and retry < OUTAGE_RETRIES):
                raise
            log.warning("job %d: %s; writing its outcome again", job_id, unavailable_message(exc))
            while not database.wait_until_reachable(OUTAGE_WAIT_S):
                if database.lost:  # gone or replaced for good: no wait brings it back
                    raise
                log.warning("job %d: the database is still unavailable; its outcome waits", job_id)


def _claim(database: Database, job_id: int) -> tuple[str, dict[str, Any], int] | None:
    with database.session(write=True) as session:
        claimed = crud.start_job(session, job_id=job_id)
        if claimed is not None:  # not queued any more: nothing to commit
            session.commit()
    return claimed


def failure_message(exc: BaseException, context: WorkerContext) -> str:
    """The job's ``message`` when it fails: the exception type and its first line, and the
    limit that was hit when memory ran out."""
    first = str(exc).splitlines()[0] if str(exc) else ""
    text = f"failed: {type(exc).__name__}" + (f": {first}" if first else "")
    out_of_memory = isinstance(exc, MemoryError) or "can't allocate memory" in str(exc)
    if out_of_memory and context.memory_mb is not None:
        limit = f"{context.memory_mb} MB (SRD_JOB_MEMORY_MB)"
        text = f"failed: the job memory limit of {limit} was reached"
    return text[:MESSAGE_LIMIT]


def _name_from_job_folder(exc: Exception, out_dir: Path) -> None:
    """A file in the job's folder that could not be written (the disk full) named from that
    folder (``cheetah.gif``): its message and error are public, and its path would say where
    the server is installed. (The folder itself keeps its path.)"""
    if not isinstance(exc, OSError):
        return
    for attribute in ("filename", "filename2"):
        name = getattr(exc, attribute)
        if isinstance(name, str) and Path(name).is_relative_to(out_dir) and Path(name) != out_dir:
            setattr(exc, attribute, Path(name).relative_to(out_dir).as_posix())


def unit_runner(context: WorkerContext, kind: str, config: Any) -> UnitRunner | None:
    """Where this job's units are computed: None (here, one after another) for the local
    backend, the Ray cluster's tasks for the ``ray`` one."""
    if context.job_backend != "ray":
        return None
    from server.jobs.ray_backend import RayRunner

    return RayRunner(
        kind,
        config,
        address=context.ray_address,
        join_timeout_s=context.ray_join_timeout_s,
        max_retries=context.ray_max_retries,
        threads=context.torch_threads,
    )


def run_job(context: WorkerContext, job_id: int) -> None:
    """Worker process entry point for one job. Whatever goes wrong once the job is claimed
    (its folder cannot be made, the experiment raises, memory runs out) is stored on the job
    by this worker before it returns: the type, the message and the innermost frames."""
    database = Database(context.database_url)
    try:
        claimed = _claim(database, job_id)
        if claimed is None:
            return
        kind, params, attempt = claimed
        out_dir = job_dir(context.data_dir, job_id)
        try:
            shutil.rmtree(out_dir, ignore_errors=True)  # leftovers of an interrupted attempt
            out_dir.mkdir(parents=True)
            check_free_disk(out_dir, context)
            progress = _Progress(
                database,
                job_id,
                attempt,
                context.progress_interval_s,
                lambda: check_disk(out_dir, context),
            )
            config = build_config(kind, params, stored=True)
            runner = unit_runner(context, kind, config)
            result = json_safe(
                run_kind(kind, config, out_dir=out_dir, progress=progress, runner=runner)
            )
            write_json(out_dir / "result.json", result)
            check_disk(out_dir, context)
            outcome: dict[str, Any] = {
                "status": JobStatus.SUCCEEDED,
                "progress": 1.0,
                "result": result,
                "message": "done",
                "artifacts": list_artifacts(out_dir),
            }
        except crud.SupersededError:
            return
        except Exception as exc:
            _name_from_job_folder(exc, out_dir)
            outcome = {  # its files are removed once it ended (``discard_unsuccessful``)
                "status": JobStatus.FAILED,
                "error": error_summary(exc),
                "message": failure_message(exc, context),
                "artifacts": [],
            }
            log.warning("job %d (%s) failed: %s", job_id, kind, outcome["error"])
        else:
            log.info("job %d (%s) succeeded", job_id, kind)
        _record_outcome(database, job_id, attempt, finished_at=utcnow(), **outcome)
    except crud.SupersededError:
        return
    finally:
        database.close()


def _cluster_lost(context: WorkerContext, exit_code: int | None) -> str | None:
    """A job worker on the Ray backend that exited with code 1 without a result: Ray ended it,
    its cluster or its node lost (``ray_backend.cluster_lost``)."""
    if context.job_backend != "ray" or exit_code != 1:
        return None
    from server.jobs.ray_backend import cluster_lost

    return cluster_lost(context.ray_address)


def discard_unsuccessful(database: Database, data_dir: str | Path, job_id: int) -> None:
    """A job whose task ended failed or cancelled (at its time limit, by a cancel, its worker
    killed) leaves no files: none of them could be downloaded (its artifacts are none). A job
    sent back to the queue (its server stopping) keeps them until it runs again."""
    try:
        with database.session(write=False) as session:
            job = crud.get_job(session, job_id=job_id)
            ended = job is not None and job.status in (JobStatus.FAILED, JobStatus.CANCELLED)
    except Exception as exc:  # the database is gone: the files wait for the job's next end
        log.warning("job %d: its files are kept: %s", job_id, exc)
        return
    if ended:
        shutil.rmtree(job_dir(data_dir, job_id), ignore_errors=True)


def requeue(session: Session, job_ids: list[int]) -> None:
    """Claimed jobs left running (their server stopped) go back to queued: they run again from
    the start, as a new attempt."""
    crud.requeue_jobs(session, job_ids=job_ids, message="re-queued: the server running it stopped")


JOB_WORK = WorkKind(
    name="job",
    table=Job,
    task=run_job,
    unfinished=JOB_UNFINISHED,
    timeout_setting="SRD_JOB_TIMEOUT_S",
    died="the job worker exited (code {code}) without a result",
    why_died=_cluster_lost,
    prepare=requeue,
    tasks_per_process=1,  # a fresh interpreter per experiment: no state carried over
)
"""Jobs as background work (``server.work.runner``)."""
