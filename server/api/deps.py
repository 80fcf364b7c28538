"""Typed dependencies of the routes: the settings, the database session, the services and the
tokens, each an ``Annotated`` type a route parameter names (``session: SessionDep``).

The services live in ``app.state.services`` (``server.services.Services``, made by the app's
lifespan); these are the only readers of ``app.state``. The ones that only look something up
are ``async def``: FastAPI runs a plain ``def`` dependency on its thread pool, a thread hop per
dependency per request for an attribute read.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import AsyncIterator, Callable
from typing import Annotated, Any, TypeVar

import anyio
import anyio.to_thread
from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection

from server.api.errors import RequestError, api_error, cut, error_item, validation_error
from server.api.readiness import Readiness
from server.api.security import token_matches
from server.auctions.arrivals import Arrivals
from server.auctions.patrons import PatronCheck
from server.auctions.sockets import RoundSockets
from server.config import Settings
from server.jobs.backend import JobCompute
from server.jobs.service import EndedJobs
from server.live.events import EventHub
from server.live.rounds import RoundWatcher
from server.screening.pool import ScreeningService
from server.services import Services
from server.store.db import READ_TIMEOUT_S, Database, DatabaseUnavailableError, first_line
from server.submissions.writer import SubmissionWriter
from server.work.runner import BackgroundRunner

T = TypeVar("T")


async def _services(connection: HTTPConnection) -> Services:
    services: Services = connection.app.state.services
    return services


ServicesDep = Annotated[Services, Depends(_services)]


async def _settings(connection: HTTPConnection) -> Settings:
    settings: Settings = connection.app.state.settings
    return settings


async def _database(services: ServicesDep) -> Database:
    return services.database


async def _screening(services: ServicesDep) -> ScreeningService:
    return services.screening


async def _submissions(services: ServicesDep) -> SubmissionWriter:
    return services.submissions


async def _rounds(services: ServicesDep) -> RoundWatcher:
    return services.rounds


async def _round_sockets(services: ServicesDep) -> RoundSockets:
    return services.sockets


async def _patrons(services: ServicesDep) -> PatronCheck:
    return services.patrons


async def _arrivals(services: ServicesDep) -> Arrivals:
    return services.arrivals


async def _auctions(services: ServicesDep) -> BackgroundRunner:
    return services.auctions


async def _jobs(services: ServicesDep) -> BackgroundRunner:
    return services.jobs


async def _compute(services: ServicesDep) -> JobCompute:
    return services.compute


async def _events(services: ServicesDep) -> EventHub:
    return services.events


async def _readiness(services: ServicesDep) -> Readiness:
    return services.readiness


async def _ended_jobs(services: ServicesDep) -> EndedJobs:
    return services.ended_jobs


SettingsDep = Annotated[Settings, Depends(_settings)]
DatabaseDep = Annotated[Database, Depends(_database)]
ScreeningDep = Annotated[ScreeningService, Depends(_screening)]
SubmissionsDep = Annotated[SubmissionWriter, Depends(_submissions)]
"""The write path of ``/submit``: one transaction per submission, on a thread of the pool."""
RoundsDep = Annotated[RoundWatcher, Depends(_rounds)]
RoundSocketsDep = Annotated[RoundSockets, Depends(_round_sockets)]
PatronsDep = Annotated[PatronCheck, Depends(_patrons)]
ArrivalsDep = Annotated[Arrivals, Depends(_arrivals)]
AuctionRunnerDep = Annotated[BackgroundRunner, Depends(_auctions)]
JobRunnerDep = Annotated[BackgroundRunner, Depends(_jobs)]
ComputeDep = Annotated[JobCompute, Depends(_compute)]
"""The job backend, as ``/healthz`` reports it."""
EventHubDep = Annotated[EventHub, Depends(_events)]
ReadinessDep = Annotated[Readiness, Depends(_readiness)]
EndedJobsDep = Annotated[EndedJobs, Depends(_ended_jobs)]

_WRITE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
log = logging.getLogger("srd.api")

_READING = "srd_reading"
"""``Session.info`` key: the read in a thread that still uses the session."""


async def _session(request: Request, database: DatabaseDep) -> AsyncIterator[Session]:
    """Request-scoped session: one transaction per request, committed by the route (a write
    session for the methods that write).

    The session is made on the event loop (no I/O until the first query). A session that
    holds no transaction (a write committed, or nothing read) is closed there too; one that
    still holds a read's transaction is closed in the thread pool, since closing rolls it back
    over the network: a database that hangs between the read and its close (stopped, cut off
    without a word) must hold that thread, never the event loop and with it every request.
    """
    if database.check_due():
        await run_in_threadpool(database.problem)
    session = database.session(write=request.method in _WRITE_METHODS)
    try:
        yield session
    finally:
        reading: asyncio.Future[Any] | None = session.info.pop(_READING, None)
        if reading is not None and not reading.done():  # a read given up on: closed later
            reading.add_done_callback(lambda _: _close_in_thread(session))
        elif session.in_transaction():
            await _close(session)
        else:
            session.close()


CLOSERS = 8
"""Threads that close read sessions at once, apart from the thread pool."""
_closers: anyio.CapacityLimiter | None = None


async def _close(session: Session) -> None:
    """Close ``session`` in a thread of its own few (``CLOSERS``), never waiting for the thread
    pool the reads use: under a burst every thread of that pool can be waiting for a
    connection held by a finished read's session, which only a close gives back (200 reads at
    once had stalled a server for 15 s and answered 185 of them 503)."""
    global _closers
    if _closers is None:  # made on the event loop, where anyio wants it
        _closers = anyio.CapacityLimiter(CLOSERS)
    await anyio.to_thread.run_sync(_close_quietly, session, limiter=_closers)


def _close_quietly(session: Session) -> None:
    """Close ``session``; a connection the database dropped meanwhile (its rollback fails) is
    one line of the log, not a traceback after the answer has gone (the pool discards it)."""
    try:
        session.close()
    except SQLAlchemyError as exc:
        log.warning("a request's session closed on a lost connection: %s", first_line(exc))


def _close_in_thread(session: Session) -> None:
    """Close ``session`` in a closing thread (from a callback on the event loop)."""
    closing = asyncio.ensure_future(_close(session))
    closing.add_done_callback(_retrieved)


SessionDep = Annotated[Session, Depends(_session)]


def _query_names(dependant: Any) -> frozenset[str]:
    """The query parameters a route (and the dependencies it uses) reads."""
    names = {field.alias for field in dependant.query_params}
    for sub in dependant.dependencies:
        names |= _query_names(sub)
    return frozenset(names)


async def known_query(connection: HTTPConnection) -> None:
    """Every API route's dependency: a query parameter the route does not read is 422 naming
    it (``/models?sttaus=held`` would otherwise answer every model, as if no filter were
    asked). Pages take any (a link may carry its own); the round socket takes none."""
    if connection.scope["type"] != "http":
        return
    route = connection.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if dependant is None:
        return
    unknown = unknown_parameter(connection, _query_names(dependant))  # about 1 µs: no cache
    if unknown is not None:
        raise unknown


def unknown_parameter(connection: HTTPConnection, known: frozenset[str]) -> RequestError | None:
    """The 422 of the first query parameter of ``connection`` not in ``known``, naming those it
    takes; None when every one is known."""
    for name in connection.query_params:
        if name not in known:
            takes = ", ".join(sorted(known)) or "none"
            return api_error(
                422,
                f"unknown query parameter {cut(name)!r} (this path takes: {takes})",
                loc=("query", name),
                kind="unknown_parameter",
            )
    return None


async def read_in_thread(fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """A request's database read in the thread pool, refused with 503 if the database has not
    answered within ``READ_TIMEOUT_S`` (a server that hangs, or is cut off without a word,
    holds no request longer). The read goes on in its thread until the database answers; a
    request session among ``args`` is closed only then."""
    reading = asyncio.ensure_future(run_in_threadpool(fn, *args, **kwargs))
    reading.add_done_callback(_retrieved)
    try:
        await asyncio.wait({reading}, timeout=READ_TIMEOUT_S)
    finally:  # given up on, or the client went away: the session waits for the thread
        if not reading.done():
            for arg in args:
                if isinstance(arg, Session):
                    arg.info[_READING] = reading
    if not reading.done():
        raise DatabaseUnavailableError(f"the database did not answer within {READ_TIMEOUT_S:g} s")
    return reading.result()


def _retrieved(reading: asyncio.Future[Any]) -> None:
    """A read's outcome is looked at even when nobody waits for it any more (no "exception
    never retrieved" at shutdown)."""
    if not reading.cancelled():
        reading.exception()


bearer_scheme = HTTPBearer(auto_error=False, description="Bearer token")
BearerDep = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)]
"""The request's bearer token, if it has one."""


async def _require_admin(services: ServicesDep, credentials: BearerDep) -> None:
    """Operator endpoints: 401 without a token, 403 with a wrong one."""
    if credentials is None:
        raise api_error(
            401,
            "operator endpoint: send 'Authorization: Bearer <admin token>'",
            loc=("header", "Authorization"),
            kind="missing_token",
        )
    if not token_matches(credentials.credentials, services.admin_token_hash):
        raise api_error(
            403,
            "the bearer token is not the admin token",
            loc=("header", "Authorization"),
            kind="bad_token",
        )


AdminDep = Depends(_require_admin)
"""In a route's ``dependencies``: the operator's token is required."""


async def _no_body(request: Request) -> None:
    """A route that takes no body: none, or ``{}``, is fine; a key is refused as every route
    refuses a key it does not know, and any other JSON (checked by ``server.api.body``) with
    422 at the body."""
    raw = await request.body()
    if not raw.strip():
        return
    value = json.loads(raw)
    if isinstance(value, dict):
        if value:
            raise validation_error(
                error_item(
                    "Extra inputs are not permitted", loc=("body", key), kind="extra_forbidden"
                )
                for key in value
            )
        return
    raise api_error(
        422, "this request takes no body: send none, or {}", loc=("body",), kind="no_body"
    )


NoBodyDep = Depends(_no_body)
"""In a route's ``dependencies`` (after the token's): the request takes no body."""


async def _participant_token(credentials: BearerDep) -> str:
    """A participant's token, required (401 without): which participant it names is the
    route's to check."""
    if credentials is None:
        raise api_error(
            401,
            "this needs the participant's token: 'Authorization: Bearer <token>'",
            loc=("header", "Authorization"),
            kind="missing_token",
        )
    return credentials.credentials


ParticipantTokenDep = Annotated[str, Depends(_participant_token)]
