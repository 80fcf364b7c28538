"""The FastAPI application: routers, error format, request-body checks, background services.

``create_app(settings)`` builds an app; its lifespan migrates the database (``alembic upgrade
head``), loads the admin token, starts the auction and job worker pools and resumes whatever a
previous run left unfinished. ``srd serve`` runs it with uvicorn.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from starlette.concurrency import run_in_threadpool

from server.auctions import AuctionRunner
from server.body import RequestBodyMiddleware
from server.config import Settings, get_settings
from server.db import Database, prepare_database
from server.errors import install_error_handlers, responses
from server.jobs import LocalJobBackend, requeue_unfinished
from server.jobs.backend import job_compute
from server.quotas import Limits
from server.remote_rounds import RoundWatcher, UploadLookup, UploadWriter
from server.routes import auctions, events, health, jobs, models, participants, rounds, ui
from server.screening import ScreeningService
from server.security import load_admin_token_hash
from server.submissions import SubmissionWriter
from server.workers import WorkerContext, freeze_heap

log = logging.getLogger("srd.app")


def _start_services(app: FastAPI, settings: Settings) -> None:
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    prepare_database(settings.database_url, settings.databases_file)
    database = Database(settings.database_url)
    context = WorkerContext(
        database_url=settings.database_url,
        data_dir=str(settings.data_dir.resolve()),
        progress_interval_s=settings.progress_interval_s,
        torch_threads=settings.worker_torch_threads,
        nice=settings.worker_nice,
    )
    app.state.database = database
    app.state.admin_token_hash = load_admin_token_hash(settings)
    app.state.auctions = AuctionRunner(
        database,
        context,
        max_workers=settings.auction_workers,
        timeout_s=settings.auction_timeout_s,
    )
    app.state.compute = job_compute(settings.job_backend, settings.ray_address)
    app.state.jobs = LocalJobBackend(
        database,
        dataclasses.replace(
            context,
            memory_mb=settings.job_memory_mb,
            job_backend=settings.job_backend,
            ray_address=settings.ray_address,
            ray_max_retries=settings.ray_max_retries,
        ),
        max_workers=settings.job_workers,
        timeout_s=settings.job_timeout_s,
    )
    app.state.screening = ScreeningService()
    app.state.screening.start()
    app.state.submissions = SubmissionWriter(database, Limits.of(settings))
    app.state.submissions.start()
    app.state.uploads = UploadWriter(database)
    app.state.uploads.start()
    app.state.upload_lookup = UploadLookup(database)
    app.state.upload_lookup.start()
    app.state.rounds = RoundWatcher(database, app.state.uploads)
    app.state.auctions.start()
    app.state.jobs.start()
    with database.session(write=True) as session:
        queued = requeue_unfinished(session)
    for job_id in queued:
        app.state.jobs.submit(job_id)
    log.info("srd server ready: %s, data in %s", settings.database_url, settings.data_dir)


def _stop_services(app: FastAPI) -> None:
    app.state.jobs.shutdown()
    app.state.auctions.shutdown()
    app.state.submissions.shutdown()
    app.state.uploads.shutdown()
    app.state.upload_lookup.shutdown()
    app.state.screening.shutdown()
    app.state.compute.close()
    app.state.database.close()


def create_app(settings: Settings | None = None) -> FastAPI:
    """The auction house application for ``settings`` (default: from the environment)."""
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await run_in_threadpool(_start_services, app, settings)
        freeze_heap()  # the imports and services live as long as the process
        try:
            yield
        finally:
            await app.state.rounds.close()
            await run_in_threadpool(_stop_services, app)

    app = FastAPI(
        title="srd-auction",
        version="0.1.0",
        summary="Fish sale auction of interpretable Self Reward Design models, and experiments.",
        lifespan=lifespan,
        docs_url=None,  # served by routes.ui with Swagger UI's files from the package (no CDN)
        redoc_url=None,
    )
    app.state.settings = settings
    install_error_handlers(app)
    app.add_middleware(RequestBodyMiddleware, max_bytes=settings.max_body_bytes)
    routers = (health, models, participants, auctions, rounds, jobs, events, ui)
    for module in routers:  # any request may carry an unreadable body
        app.include_router(module.router, responses=responses(400, 413, 415))
    app.state.routes = [route for module in routers for route in module.router.routes]
    return app
