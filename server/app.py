"""The FastAPI application: routers, error format, request-body checks, background services.

``create_app(settings)`` builds an app; its lifespan starts the services
(``server.services.start_services``: migrations, the admin token, the screener, the writers,
the auction and job runners, which resume whatever a previous run left unfinished) and stops
them. ``srd serve`` runs it with uvicorn.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI
from starlette.concurrency import run_in_threadpool

from server.api.body import RequestBodyMiddleware
from server.api.deps import known_query
from server.api.errors import install_error_handlers, responses
from server.api.hardening import SecurityHeadersMiddleware
from server.api.limits import ClientLimitsMiddleware
from server.api.routes import (
    auctions,
    events,
    health,
    jobs,
    models,
    participants,
    reviews,
    rounds,
)
from server.config import Settings, get_settings
from server.services import start_services
from server.ui import routes as ui
from server.work.pool import freeze_heap

log = logging.getLogger("srd.app")

EVENT_STREAM = "text/event-stream"

EVERY_ROUTE = (400, 413, 414, 415, 429, 503)
"""What any request may be answered, whatever its route: an unreadable request or body, a
query too long, a body that is not JSON, the address's request rate or share spent, the
database or the server's connections unavailable."""


class _App(FastAPI):
    def openapi(self) -> dict[str, Any]:
        """FastAPI's document, with an event stream's errors said as what they are, JSON:
        FastAPI gives every answer of a route the route's media type (``text/event-stream``),
        while an error is answered before any stream starts."""
        if self.openapi_schema is None:
            for path in super().openapi()["paths"].values():
                for operation in path.values():
                    for code, answer in operation["responses"].items():
                        content = answer.get("content", {})
                        if code.isdigit() and int(code) >= 400 and EVENT_STREAM in content:
                            content["application/json"] = content.pop(EVENT_STREAM)
        assert self.openapi_schema is not None
        return self.openapi_schema


def create_app(settings: Settings | None = None) -> FastAPI:
    """The auction house application for ``settings`` (default: from the environment)."""
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services = await run_in_threadpool(start_services, settings)
        app.state.services = services  # read by server.api.deps only
        services.live.start()
        loop = asyncio.get_running_loop()
        # ``srd serve`` calls this from its signal handler: waiting long polls answer at once
        app.state.drain = lambda: loop.call_soon_threadsafe(services.live.drain)
        freeze_heap()  # the imports and services live as long as the process
        services.judge_left_pending()  # what a killed server left pending in closed rounds
        try:
            yield
        finally:
            await services.close()
            await run_in_threadpool(services.stop)

    app = _App(
        title="srd-auction",
        version="0.1.0",
        summary="Fish sale auction of interpretable Self Reward Design models, and experiments.",
        lifespan=lifespan,
        docs_url=None,  # served by server.ui with Swagger UI's files from the package (no CDN)
        redoc_url=None,
        redirect_slashes=False,  # /models/ is 404, not a redirect built from the Host header
    )
    app.state.settings = settings
    install_error_handlers(app)
    app.add_middleware(events.StreamLeftMiddleware)
    app.add_middleware(
        RequestBodyMiddleware, max_bytes=settings.max_body_bytes, smaller=(rounds.UPLOAD_BODY,)
    )
    app.add_middleware(ClientLimitsMiddleware, settings=settings)  # before any body is read
    app.add_middleware(  # outermost: every answer has its headers
        SecurityHeadersMiddleware, allowed_hosts=settings.allowed_host_names
    )
    routers = (health, models, reviews, participants, auctions, rounds, jobs, events, ui)
    for module in routers:  # any request may carry an unreadable body
        checks = [] if module is ui else [Depends(known_query)]  # API routes: no unknown query
        app.include_router(module.router, responses=responses(*EVERY_ROUTE), dependencies=checks)
    app.state.routes = [  # the app's own (the OpenAPI document), then the routers'
        *(route for route in app.routes if getattr(route, "path", None)),
        *(route for module in routers for route in module.router.routes),
    ]
    return app
