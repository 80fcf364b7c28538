"""Server-Sent Event streams: ``GET /auctions/{id}/events`` and ``GET /jobs/{id}/events``.

An auction's stream sends ``event: iteration`` once per committed iteration, with ``id`` = the
round's iteration (0, 1, ...) and ``data`` = the round with its purchases and quits. A remote
fine-tuning round, which follows iteration k, adds ``event: round`` with ``id`` = ``k.1`` when
it is open and ``k.2`` once it has closed (a round already closed when it is sent gets only
``k.2``). When the auction has finished or failed, ``event: end`` (no id) gives the outcome and
the stream closes. A job's stream sends ``event: progress`` whenever its status, progress or
message changes (``id`` = the time of that change, in microseconds), then ``event: end`` with
the whole job.

A client resumes with ``Last-Event-ID`` (what ``EventSource`` sends when it reconnects) or, on
its first connection, ``?after=<id>``: the stream goes on right after that event, so nothing is
skipped and nothing repeated. Idle streams send a comment every ``SRD_EVENT_KEEPALIVE_S``.
Everything sent is read from committed rows by the process's live-update source, once per
change of the auction or job whatever the number of streams (``server.live.source``).
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterable, AsyncIterator, Iterator
from dataclasses import dataclass
from typing import Annotated

import anyio
from fastapi import APIRouter, Depends, Header, Query, Request
from fastapi.sse import EventSourceResponse, ServerSentEvent
from pydantic import BeforeValidator
from sqlalchemy.orm import Session
from starlette.types import ASGIApp, Receive, Scope, Send

from server.api.deps import (
    BearerDep,
    DatabaseDep,
    EventHubDep,
    ServicesDep,
    SettingsDep,
    read_in_thread,
)
from server.api.errors import api_error, responses
from server.api.routes.auctions import fine_tune_round_public, iteration_public
from server.api.schemas import (
    AuctionEndEvent,
    AuctionIdPath,
    IterationEvent,
    JobIdPath,
    JobProgressEvent,
    JobPublic,
    PatronPublic,
    RoundPurchasePublic,
)
from server.api.schemas.common import true_or_false
from server.api.security import token_matches
from server.auctions import service as auctions
from server.jobs import service as jobs
from server.live.events import EventHub
from server.store import crud
from server.store.status import AUCTION_ENDED, JOB_ENDED, RoundStatus
from server.store.tables import Job


async def _chunks_allowed(request: Request) -> None:
    """A stream is sent in chunks (its length is not known), which HTTP/1.0 has not: a client
    that asks over HTTP/1.0 is told so (505), instead of reading chunk sizes in its events."""
    if request.scope.get("http_version") == "1.0":
        raise api_error(
            505,
            "an event stream is sent in chunks, which HTTP/1.0 has not: ask over HTTP/1.1",
            loc=("connection",),
            kind="http_version",
        )


router = APIRouter(tags=["events"], dependencies=[Depends(_chunks_allowed)])
log = logging.getLogger("srd.events")

RETRY_AFTER_S = 5
"""What a client refused for want of stream slots is told to wait (``Retry-After``)."""
RECONNECT_MS = 2000
"""The ``retry:`` hint: how long ``EventSource`` waits before it reconnects a dropped stream."""
EVENT_ID = r"^[0-9]{1,18}(\.[12])?$"
"""An auction's event id: an iteration, or ``k.1``/``k.2`` for the fine-tuning round after
iteration k."""
JOB_EVENT_ID = r"^[0-9]{1,18}$"
"""A job's event id: its change time in microseconds."""
ROUND_OPEN, ROUND_CLOSED = 1, 2

LastEventId = Annotated[
    str | None,
    Header(
        alias="Last-Event-ID",
        pattern=EVENT_ID,
        description="The id of the last event received; the stream resumes right after it.",
    ),
]
After = Annotated[
    str | None,
    Query(
        pattern=EVENT_ID,
        description="Like Last-Event-ID, for a first connection (the header wins if both).",
    ),
]
Position = tuple[int, int]
"""Where an event sits in an auction's stream: (iteration, 0) for the iteration itself, then
(iteration, ROUND_OPEN or ROUND_CLOSED) for the fine-tuning round that follows it."""


def _position(event_id: str) -> Position:
    iteration, _, phase = event_id.partition(".")
    return int(iteration), int(phase or 0)


@dataclass(frozen=True)
class Resume:
    """The event a client says it has: its id, and where it said so."""

    event_id: str
    loc: tuple[str, str]


def _resume_id(last_event_id: LastEventId = None, after: After = None) -> Resume | None:
    if last_event_id is not None:
        return Resume(last_event_id, ("header", "Last-Event-ID"))
    return None if after is None else Resume(after, ("query", "after"))


async def _auction_resume(resume: Annotated[Resume | None, Depends(_resume_id)]) -> Position:
    """Where an auction's stream resumes: after this position (before the first event if
    none)."""
    return (-1, ROUND_CLOSED) if resume is None else _position(resume.event_id)


async def _job_resume(
    last_event_id: Annotated[
        str | None,
        Header(
            alias="Last-Event-ID",
            pattern=JOB_EVENT_ID,
            description="The id of the last event received (a whole number); the stream "
            "resumes right after it.",
        ),
    ] = None,
    after: Annotated[
        str | None,
        Query(
            pattern=JOB_EVENT_ID,
            description="Like Last-Event-ID, for a first connection (the header wins if both).",
        ),
    ] = None,
) -> str | None:
    """The id of the last job event the client has."""
    return last_event_id if last_event_id is not None else after


def _event_id(position: Position) -> str:
    iteration, phase = position
    return f"{iteration}.{phase}" if phase else str(iteration)


async def _stream_slot(
    hub: EventHubDep, services: ServicesDep, credentials: BearerDep
) -> AsyncIterator[EventHub]:
    """Hold one of the process's stream slots for the whole stream; 503 when none is free,
    except to the operator, whose streams (at most its client share) are always served."""
    operator = credentials is not None and token_matches(
        credentials.credentials, services.admin_token_hash
    )
    if not hub.acquire(reserved=operator):
        raise api_error(
            503,
            f"{hub.max_streams} event streams are open, the most this server holds; retry later",
            loc=("server",),
            kind="too_many_streams",
            headers={"Retry-After": str(RETRY_AFTER_S)},
        )
    try:
        yield hub
    finally:
        hub.release()


StreamSlot = Annotated[EventHub, Depends(_stream_slot)]


# --- auctions ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class AuctionSnapshot:
    """An auction as its stream shows it: where it stands and every committed iteration."""

    state: crud.AuctionState | None
    rounds: tuple[crud.AuctionRound, ...]
    fine_tuning: tuple[crud.RoundView, ...] = ()

    @property
    def final(self) -> bool:
        return self.state is None or self.state.status in AUCTION_ENDED

    def events_after(
        self, sent: Position, *, rounds: bool
    ) -> Iterator[tuple[Position, ServerSentEvent]]:
        """The events of this snapshot that come after ``sent``, in stream order (built only
        for those: a listener that is up to date costs nothing); the fine-tuning rounds' too
        if ``rounds``."""
        fine_tuning = {view.iteration: view for view in self.fine_tuning} if rounds else {}
        for row in self.rounds[max(sent[0], 0) :]:
            position = (row.iteration, 0)
            if position > sent:
                yield position, _iteration_sse(row)
            view = fine_tuning.get(row.iteration)
            if view is not None:
                phase = ROUND_OPEN if view.status == RoundStatus.OPEN else ROUND_CLOSED
                position = (row.iteration, phase)
                if position > sent:
                    yield position, _round_sse(view, position)


def auction_view(
    session: Session,
    auction_id: int,
    state: crud.AuctionState | None,
    previous: AuctionSnapshot | None,
) -> AuctionSnapshot:
    """What an auction's stream shows: its state, then only the rounds committed since."""
    rounds = () if previous is None else previous.rounds
    if state is None:
        return AuctionSnapshot(None, rounds)
    if state.iteration > len(rounds):
        new = crud.auction_rounds(
            session, auction_id=auction_id, first=len(rounds), stop=state.iteration
        )
        rounds = (*rounds, *new)
    fine_tuning: tuple[crud.RoundView, ...] = ()
    if state.fine_tune_mode == "remote":
        fine_tuning = tuple(crud.fine_tune_rounds(session, auction_id=auction_id))
    return AuctionSnapshot(state, rounds, fine_tuning)


def _patron(ref: crud.PatronRef) -> PatronPublic:
    return PatronPublic(
        model_id=ref.model_id,
        participant=ref.participant,
        version=ref.version,
        version_id=ref.version_id,
    )


def iteration_event(row: crud.AuctionRound) -> IterationEvent:
    """The ``data`` of one round's event."""
    return IterationEvent(
        **dict(iteration_public(row)),
        purchases=[
            RoundPurchasePublic(**_patron(p.patron).model_dump(), price=p.price)
            for p in row.purchases
        ],
        quits=[_patron(ref) for ref in row.quits],
    )


def _iteration_sse(row: crud.AuctionRound) -> ServerSentEvent:
    return ServerSentEvent(event="iteration", id=str(row.iteration), data=iteration_event(row))


def _round_sse(view: crud.RoundView, position: Position) -> ServerSentEvent:
    return ServerSentEvent(event="round", id=_event_id(position), data=fine_tune_round_public(view))


def auction_end_event(state: crud.AuctionState) -> AuctionEndEvent:
    """The ``data`` of an auction's last event."""
    return AuctionEndEvent(
        status=state.status,  # one of AUCTION_ENDED
        iterations=state.iteration,
        price=state.price,
        n_available=state.n_available,
        n_initial=state.n_initial,
        n_sold=state.n_initial - state.n_available,
        stop_reason=state.stop_reason,
        error=state.error,
        finished_at=state.finished_at,
    )


async def _existing_auction(
    auction_id: AuctionIdPath,
    database: DatabaseDep,
    resume: Annotated[Resume | None, Depends(_resume_id)],
) -> int:
    """The auction's id, once it is known to exist and to have sent the event the client says
    it has (an id ahead of its stream would wait for events that never come, or skip some)."""

    position = None if resume is None else _position(resume.event_id)

    def read() -> tuple[crud.AuctionState, str | None]:
        """The auction, and why a round's id after its last iteration was never sent."""
        with database.session(write=False) as session:
            state = auctions.require_auction(session, auction_id)
            if position is None or not position[1] or position[0] != state.iteration - 1:
                return state, None
            after = crud.round_status_after(session, auction_id=auction_id, iteration=position[0])
        if after is None:
            return state, "no fine-tuning round after it"
        if after == RoundStatus.OPEN and position[1] == ROUND_CLOSED:
            return state, "its round open"
        return state, None

    state, unsent = await read_in_thread(read)
    if resume is not None and unsent is not None:
        raise api_error(
            422,
            f"event {resume.event_id} is ahead of auction {auction_id}'s stream: its iteration "
            f"{state.iteration - 1} has {unsent}"
            + ("" if state.status in AUCTION_ENDED else " so far"),
            loc=resume.loc,
            kind="ahead",
        )
    if resume is not None and position is not None and position[0] >= state.iteration:
        if state.iteration == 0:
            sent = "no iteration"
        elif state.iteration == 1:
            sent = "iteration 0"
        else:
            sent = f"iterations 0 to {state.iteration - 1}"
        raise api_error(
            422,
            f"event {resume.event_id} is ahead of auction {auction_id}'s stream, which has "
            f"sent {sent}" + ("" if state.status in AUCTION_ENDED else " so far"),
            loc=resume.loc,
            kind="ahead",
        )
    return auction_id


@router.get(
    "/auctions/{auction_id}/events",
    response_class=EventSourceResponse,
    operation_id="auction_events",
    openapi_extra={"security": [{}]},  # a token is optional (the operator's is served first)
    responses=responses(404, 422, 429, 503, 505),
)
async def auction_events(
    resume: Annotated[Position, Depends(_auction_resume)],
    hub: StreamSlot,
    auction_id: Annotated[int, Depends(_existing_auction)],
    settings: SettingsDep,
    rounds: Annotated[
        bool,
        Query(
            description="Also send the remote fine-tuning rounds, as `round` events (`id` = "
            "`k.1` when the round after iteration k opens, `k.2` when it closes). Without it "
            "the stream holds iterations only, each `id` a whole number."
        ),
        BeforeValidator(true_or_false),
    ] = False,
) -> AsyncIterable[ServerSentEvent]:
    """Follow an auction live: one ``iteration`` event per committed iteration (``id`` = the
    iteration), with ``?rounds=true`` ``round`` events for remote fine-tuning rounds (``id`` =
    ``k.1`` open, ``k.2`` closed, after iteration k), then one ``end`` event, and the stream
    closes."""
    sent = resume  # the last event the client has
    async with hub.watch("auction", auction_id, auction_view) as watch:
        yield ServerSentEvent(comment=f"auction {auction_id}", retry=RECONNECT_MS)
        while True:
            generation, snapshot = watch.generation, watch.snapshot
            assert snapshot is not None  # auction_view and job_view always give one
            for position, event in snapshot.events_after(sent, rounds=rounds):
                yield event
                sent = position
            if snapshot.final:
                if snapshot.state is not None:
                    yield ServerSentEvent(event="end", data=auction_end_event(snapshot.state))
                return
            if not await watch.wait(generation, settings.event_keepalive_s):
                yield ServerSentEvent(comment="keep-alive")
            if hub.source.draining:  # shutting down: the client resumes from its last id
                return


# --- jobs -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class JobSnapshot:
    """A job as its stream shows it; the whole job once it has ended."""

    state: crud.JobState | None
    job: str | None
    """The whole job's JSON, encoded once for every stream that sends it."""

    @property
    def final(self) -> bool:
        return self.state is None or self.state.status in JOB_ENDED


def job_view(
    session: Session, job_id: int, state: crud.JobState | None, previous: JobSnapshot | None
) -> JobSnapshot:
    """What a job's stream shows: its state, and the whole job once it has ended."""
    job = None
    if state is not None and state.status in JOB_ENDED:
        row = session.get(Job, job_id)
        if row is not None:
            job = JobPublic.model_validate(row, from_attributes=True).model_dump_json()
    return JobSnapshot(state, job)


def job_event_id(state: crud.JobState) -> str:
    """A job event's id: when the job row last changed, in microseconds since the epoch."""
    return str(int(state.updated_at.timestamp() * 1_000_000))


async def _existing_job(job_id: JobIdPath, database: DatabaseDep) -> int:
    def read() -> None:
        with database.session(write=False) as session:
            jobs.require_job(session, job_id)

    await read_in_thread(read)
    return job_id


@router.get(
    "/jobs/{job_id}/events",
    response_class=EventSourceResponse,
    operation_id="job_events",
    openapi_extra={"security": [{}]},  # a token is optional (the operator's is served first)
    responses=responses(404, 422, 429, 503, 505),
)
async def job_events(
    resume: Annotated[str | None, Depends(_job_resume)],
    hub: StreamSlot,
    job_id: Annotated[int, Depends(_existing_job)],
    settings: SettingsDep,
) -> AsyncIterable[ServerSentEvent]:
    """Follow a job: a ``progress`` event whenever its status, progress or message changes,
    then one ``end`` event with the whole job (result, error, artifacts), and the stream
    closes."""
    seen = resume
    async with hub.watch("job", job_id, job_view) as watch:
        yield ServerSentEvent(comment=f"job {job_id}", retry=RECONNECT_MS)
        while True:
            generation, snapshot = watch.generation, watch.snapshot
            assert snapshot is not None  # auction_view and job_view always give one
            if snapshot.state is None:
                return
            if snapshot.final:
                yield ServerSentEvent(event="end", raw_data=snapshot.job)
                return
            event_id = job_event_id(snapshot.state)
            if event_id != seen:
                progress = JobProgressEvent(
                    status=snapshot.state.status,
                    progress=snapshot.state.progress,
                    message=snapshot.state.message,
                )
                yield ServerSentEvent(event="progress", id=event_id, data=progress)
                seen = event_id
            if not await watch.wait(generation, settings.event_keepalive_s):
                yield ServerSentEvent(comment="keep-alive")
            if hub.source.draining:  # shutting down: the client resumes from its last id
                return


class StreamLeftMiddleware:
    """A client that leaves an event stream is no error. FastAPI's ``EventSourceResponse``
    closes the stream's output before it stops the task that fills it, so a client that goes
    away while that task waits on a full buffer (a slow reader: the socket pushed back) ends
    the request with an ``ExceptionGroup`` of ``BrokenResourceError``, which uvicorn logged as
    "Exception in ASGI application" with a traceback. That, and only that, is logged here at
    debug level."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope["path"].endswith("/events"):
            await self.app(scope, receive, send)
            return
        try:
            await self.app(scope, receive, send)
        except* (anyio.BrokenResourceError, anyio.ClosedResourceError):
            log.debug("the client of %s left while the stream was full", scope["path"])
