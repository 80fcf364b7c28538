"""The running services of one API process, started and stopped by the app's lifespan.

``Services`` holds them (the database, the screening pool, the submissions' writer, the two
background runners, the round watcher and sockets, the live-update source, the job backend);
``start_services`` makes and starts them, ``Services.stop`` stops them. The operations the
routes call live with their concern (``server.auctions.service`` and ``.uploads``,
``server.jobs.service``, ``server.submissions.service``): they take the services they need and
the request's values, do the work, and return domain values or raise
``server.api.errors.RequestError``; the routes translate HTTP to and from them.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
import secrets
import socket
from dataclasses import dataclass, field

from sqlalchemy.engine import make_url

from server.api.readiness import Readiness
from server.api.security import load_admin_token_hash
from server.auctions.arrivals import Arrivals
from server.auctions.patrons import PatronCheck
from server.auctions.sockets import RoundSockets
from server.auctions.steps import AUCTION_WORK
from server.auctions.uploads import judge_left_pending
from server.config import Settings
from server.jobs.backend import JobCompute, job_compute
from server.jobs.service import ENDED_JOBS_BYTES, EndedJobs
from server.jobs.worker import JOB_WORK, discard_unsuccessful
from server.live.events import EventHub
from server.live.rounds import RoundWatcher
from server.live.source import LiveSource
from server.screening.pool import ScreeningService
from server.store import crud
from server.store.db import (
    Database,
    SqliteServerLock,
    is_sqlite,
    owned_url,
    prepare_database,
)
from server.submissions.quotas import Limits
from server.submissions.writer import SubmissionWriter
from server.work.pool import WorkerContext, usable_cpus
from server.work.runner import BackgroundRunner, WorkKind

log = logging.getLogger("srd.services")


@dataclass
class Services:
    """The running services of one API process."""

    settings: Settings
    database: Database
    admin_token_hash: str
    screening: ScreeningService
    submissions: SubmissionWriter
    rounds: RoundWatcher
    sockets: RoundSockets
    """The round sockets (``WS /auctions/{id}/rounds/socket``), pushed by ``rounds``."""
    patrons: PatronCheck
    """Whose round requests are a patron's (their share of sockets and long polls)."""
    arrivals: Arrivals
    """When the round uploads without an answer first arrived (their retries' arrival): in
    memory, and journaled in ``<data_dir>/arrivals/`` for a restart after ``kill -9``."""
    auctions: BackgroundRunner
    jobs: BackgroundRunner
    compute: JobCompute
    events: EventHub
    live: LiveSource
    """The one live-update source, shared by ``events``, ``rounds`` and ``sockets``."""
    sqlite_lock: SqliteServerLock | None
    """Held while this process serves a SQLite database (None on PostgreSQL)."""
    readiness: Readiness
    ended_jobs: EndedJobs
    """The JSON of ended jobs, as ``GET /jobs/{id}`` sends it."""
    sweeps: set[asyncio.Task[int]] = field(default_factory=set)
    """The judging of uploads closed rounds left pending, running (``judge_left_pending``)."""

    def judge_left_pending(self, auction_id: int | None = None) -> None:
        """Judge, in the background on the event loop, the uploads that closed rounds left
        pending (of ``auction_id`` only, if given): at start, and after a cancel, in a task of
        its own (a request's background task would run while the request still holds its
        session, and wait for SQLite's write lock that session holds)."""
        sweep = asyncio.get_running_loop().create_task(
            judge_left_pending(
                self.database,
                self.screening,
                margin=self.settings.review_margin,
                auction_id=auction_id,
            )
        )
        self.sweeps.add(sweep)
        sweep.add_done_callback(self.sweeps.discard)

    async def close(self) -> None:
        """Stop what runs on the event loop (the live-update source's reads and listener, the
        judging of uploads left pending)."""
        for sweep in list(self.sweeps):
            sweep.cancel()
        await asyncio.gather(*self.sweeps, return_exceptions=True)
        await self.live.close()

    def stop(self) -> None:
        """Stop every worker and writer, then let go of the database (blocking); each part is
        stopped even if one before it failed (a database outage had left the screening process
        and the database's connections behind)."""
        parts = [
            ("the job runner", self.jobs.shutdown),
            ("the auction runner", self.auctions.shutdown),
            ("the screening process", self.screening.shutdown),
            ("the job backend", self.compute.close),
            ("the database", self.database.close),
            ("the arrivals journal", self.arrivals.close),
        ]
        if self.sqlite_lock is not None:
            parts.append(("the SQLite lock", self.sqlite_lock.release))
        for name, stop in parts:
            try:
                stop()
            except Exception:
                log.exception("stopping %s failed", name)


def server_id() -> str:
    """This process's lease owner id: host, process id and a random part (a restarted process
    with the same pid is another owner)."""
    return f"{socket.gethostname()[:60]}:{os.getpid()}:{secrets.token_hex(4)}"


def screener_populations(settings: Settings) -> str:
    """The marker of the populations the screener meets under ``settings``
    (``screener.secret.marker_of``)."""
    from screener.secret import marker_of

    secret = settings.screener_secret
    return marker_of("" if secret is None else secret.get_secret_value())


def _key_the_screener(settings: Settings, database: Database) -> None:
    """Hand ``SRD_SCREENER_SECRET`` (perhaps from a secret file) to the processes this server
    starts that screen, and say which populations they meet: a warning when the newest verdict
    was made on others (the secret changed, or another replica has another)."""
    from screener.secret import SECRET_VARIABLE

    secret = settings.screener_secret
    if secret is None:
        os.environ.pop(SECRET_VARIABLE, None)
    else:
        os.environ[SECRET_VARIABLE] = secret.get_secret_value()
    marker = screener_populations(settings)
    with database.session(write=False) as session:
        newest = crud.newest_populations(session)
    log.info(
        "screener: the market-impact test meets the %s populations",
        "public" if secret is None else f"SRD_SCREENER_SECRET's ({marker})",
    )
    if newest is not None and newest != marker:
        log.warning(
            "screener: the newest verdict stored was made on other populations (%s) than this "
            "server's (%s): SRD_SCREENER_SECRET changed, or another replica has another; "
            "replicas that differ give one model two verdicts",
            newest,
            marker,
        )


def start_services(settings: Settings) -> Services:
    """Take the SQLite database's one-server lock (refusing to start beside another server),
    migrate the database, then make and start every service; the runners claim the unfinished
    auctions and jobs they may (blocking)."""
    sqlite_lock = (
        SqliteServerLock(settings.database_url) if is_sqlite(settings.database_url) else None
    )
    try:
        return _start(settings, sqlite_lock)
    except BaseException:
        if sqlite_lock is not None:
            sqlite_lock.release()
        raise


def _start(settings: Settings, sqlite_lock: SqliteServerLock | None) -> Services:
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    prepare_database(settings.database_url, settings.databases_file)
    owner = server_id()
    url = owned_url(settings.database_url, owner)  # its sessions named for its leases
    database = Database(url)
    _key_the_screener(settings, database)  # before the processes that screen start
    context = WorkerContext(
        database_url=url,
        data_dir=str(settings.data_dir.resolve()),
        progress_interval_s=settings.progress_interval_s,
        torch_threads=settings.worker_torch_threads,
        review_margin=settings.review_margin,
        log_level=logging.getLogger().getEffectiveLevel(),  # as ``srd serve`` set it
    )  # auction steps at the API's priority: the next round waits for its step
    job_context = dataclasses.replace(
        context,
        nice=settings.worker_nice,
        memory_mb=settings.job_memory_mb,
        job_disk_mb=settings.job_disk_mb,
        min_free_disk_mb=settings.min_free_disk_mb,
        job_backend=settings.job_backend,
        ray_address=settings.ray_address,
        ray_join_timeout_s=settings.ray_join_timeout_s,
        ray_max_retries=settings.ray_max_retries,
    )
    live = LiveSource(
        database,
        poll_s=settings.event_poll_interval_s,
        safety_poll_s=settings.live_safety_poll_s,
    )
    watcher = RoundWatcher(live)

    def runner(
        kind: WorkKind, context: WorkerContext, max_workers: int, timeout_s: float
    ) -> BackgroundRunner:
        def ended(row_id: int) -> None:  # a step's or a job's last commit: its watchers hear now
            live.committed_elsewhere("auction" if kind is AUCTION_WORK else "job", row_id)
            if kind is JOB_WORK:
                discard_unsuccessful(database, settings.data_dir, row_id)

        return BackgroundRunner(
            database,
            context,
            kind,
            max_workers=max_workers,
            timeout_s=timeout_s,
            owner=owner,
            lease_s=settings.lease_s,
            exclusive=sqlite_lock is not None,
            ended=ended,
        )

    screening = ScreeningService()
    arrivals = Arrivals(settings.data_dir / "arrivals")
    services = Services(
        settings=settings,
        database=database,
        admin_token_hash=load_admin_token_hash(settings),
        screening=screening,
        submissions=SubmissionWriter(database, Limits.of(settings)),
        rounds=watcher,
        sockets=RoundSockets(watcher),
        patrons=PatronCheck(database),
        arrivals=arrivals,
        auctions=runner(
            AUCTION_WORK,
            context,
            settings.auction_workers or usable_cpus(),
            settings.auction_timeout_s,
        ),
        jobs=runner(JOB_WORK, job_context, settings.job_workers, settings.job_timeout_s),
        compute=job_compute(
            settings.job_backend, settings.ray_address, settings.ray_join_timeout_s
        ),
        events=EventHub(live, max_streams=settings.max_event_streams),
        live=live,
        sqlite_lock=sqlite_lock,
        readiness=Readiness(
            database, settings.data_dir, settings.min_free_disk_mb, screening.problem
        ),
        ended_jobs=EndedJobs(ENDED_JOBS_BYTES),
    )
    services.screening.start()
    live.when_due("auction", services.auctions.wake)
    live.when_due("job", services.jobs.wake)
    if arrivals.unanswered_at_start:  # killed with uploads read but not stored: their
        # retries come before any step closes their round
        log.warning(
            "%d round uploads arrived before the last stop without an answer: their retries "
            "are judged by that arrival; no auction step for a few seconds",
            arrivals.unanswered_at_start,
        )
        database.hold_claims()
    services.auctions.start()
    services.jobs.start()
    shown = make_url(settings.database_url).render_as_string(hide_password=True)
    log.info("srd server ready: %s, data in %s", shown, settings.data_dir)
    return services
