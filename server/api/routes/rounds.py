"""Remote fine-tuning rounds: ``GET /auctions/{id}/rounds/current`` publishes the newest round
(long poll with ``?wait=``), ``PUT /auctions/{id}/rounds/{round}/models/{model_id}`` takes a
patron's fine-tuned manifest, re-screens it and stores it as a new version (the checks:
``server.auctions.uploads``); ``WS /auctions/{id}/rounds/socket`` is the same over one
WebSocket per agent (``server.auctions.sockets``).
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import Callable, Coroutine
from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Header, Path, Query, Request, Response, WebSocket
from pydantic import BeforeValidator

from server.api.connections import PIPELINED_BEHIND, RECEIVED_AT
from server.api.deps import (
    ArrivalsDep,
    AuctionRunnerDep,
    DatabaseDep,
    ParticipantTokenDep,
    PatronsDep,
    RoundsDep,
    RoundSocketsDep,
    ScreeningDep,
    SettingsDep,
    unknown_parameter,
)
from server.api.errors import RequestError, api_error, problem_response, responses
from server.api.limits import client_limits
from server.api.schemas import (
    MAX_FINE_TUNE_ROUNDS,
    AuctionIdPath,
    ModelIdPath,
    RoundPublic,
    UploadPublic,
)
from server.api.schemas.common import decimal_only, digits_only
from server.auctions import patrons as patron_shares
from server.auctions import uploads as rounds
from server.auctions.service import not_found
from server.auctions.sockets import RETRY_AFTER_S, UPLOAD_MAX_BYTES, SocketLimitError
from server.live.rounds import MAX_WAIT_S, TooManyWaitersError
from server.store.tables import utcnow

router = APIRouter(tags=["rounds"])

UPLOAD_BODY = (
    "PUT",
    re.compile(r"/auctions/[^/]+/rounds/[^/]+/models/[^/]+"),
    UPLOAD_MAX_BYTES,
    f"an upload is at most {UPLOAD_MAX_BYTES} bytes",
)
"""The round upload's body bound, for ``RequestBodyMiddleware``: refused by its size before
anything else is read (the route's path, whatever its segments hold)."""

RoundPath = Annotated[
    int,
    Path(
        alias="round",
        ge=1,
        le=MAX_FINE_TUNE_ROUNDS,
        description="A fine-tuning round (1 follows iteration 0, 2 iteration 1, ...).",
    ),
    BeforeValidator(digits_only),
]


@router.get(
    "/auctions/{auction_id}/rounds/current",
    operation_id="read_current_round",
    response_class=Response,
    responses={
        200: {"model": RoundPublic, "description": "The auction's newest fine-tuning round"},
        **responses(404, 422, 503),
    },
)
async def read_current_round(
    request: Request,
    auction_id: AuctionIdPath,
    watcher: RoundsDep,
    patrons: PatronsDep,
    authorization: Annotated[
        str | None,
        Header(
            description="A patron's ``Bearer <participant token>`` (optional): its long polls "
            "have a share apart from everyone else's."
        ),
    ] = None,
    wait: Annotated[
        float,
        Query(
            ge=0,
            le=MAX_WAIT_S,
            allow_inf_nan=False,
            description="Seconds to wait for a round above ``after`` to open (or the end).",
        ),
        BeforeValidator(decimal_only),
    ] = 0.0,
    after: Annotated[
        int,
        Query(ge=0, le=MAX_FINE_TUNE_ROUNDS, description="The last round the client handled."),
        BeforeValidator(digits_only),
    ] = 0,
) -> Response:
    """The auction's newest fine-tuning round: status open | closed | none, its deadline
    (UTC) and seconds left; while open the item rows, the seeds and the patrons asked. With
    ``wait`` the answer comes as soon as a round numbered above ``after`` is open or the
    auction has ended, and at the latest after ``wait`` seconds. When everyone else's share of
    waits is full, a patron that sends its token waits in the patrons' own."""
    token = _bearer(authorization)

    async def claim() -> Callable[[], None] | None:
        release = await patrons.claim(auction_id, token)
        if release is None and await patrons.is_patron(auction_id, token):
            raise TooManyWaitersError(_share_taken(auction_id, "long polls"))
        return release

    def answer(wait_s: float) -> Coroutine[Any, Any, bytes]:
        return rounds.current_round(watcher, auction_id, wait_s=wait_s, after=after, claim=claim)

    if wait == 0:
        return Response(await answer(0.0), media_type="application/json")
    body = await _unless_gone(request, answer(wait), request.scope.get(PIPELINED_BEHIND))
    if body is None:  # a request was pipelined behind it: it answers now, as at its end
        body = await answer(0.0)
    return Response(body, media_type="application/json")


async def _unless_gone(
    request: Request, answer: Coroutine[Any, Any, bytes], behind: object
) -> bytes | None:
    """``answer``, unless the client goes away first: then the wait is cancelled at once, so
    it frees its share of the waits (and its client's long polls) now, not when it would
    have ended (up to ``MAX_WAIT_S`` later); what is returned then is never sent. None, the
    wait cancelled, once ``behind`` (``srd serve``'s event of a request pipelined behind this
    one on its connection) is set: that request waits for this answer."""
    waiting = asyncio.ensure_future(answer)
    others: list[asyncio.Future[Any]] = [asyncio.ensure_future(_disconnected(request))]
    if isinstance(behind, asyncio.Event):
        others.append(asyncio.ensure_future(behind.wait()))
    try:
        await asyncio.wait({waiting, *others}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for other in others:
            other.cancel()
        if not waiting.done():
            waiting.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await waiting
    if not waiting.cancelled():
        return waiting.result()
    return None if isinstance(behind, asyncio.Event) and behind.is_set() else b""


async def _disconnected(request: Request) -> None:
    """Until the client has gone away (a GET's empty body was read already: the next
    message is the disconnect)."""
    while (await request.receive())["type"] != "http.disconnect":
        pass


async def _upload_body(request: Request) -> tuple[bytes, datetime]:
    """The request body (at most ``UPLOAD_MAX_BYTES``: ``UPLOAD_BODY``, 413 before the token
    or the JSON is read), and when it arrived (the deadline is judged at that moment): when
    ``srd serve``'s protocol parsed its last byte, else when it was read here."""
    body = await request.body()
    if not body:  # as the body checks refuse any body that is not JSON, before the token
        raise api_error(
            422, "the body is empty: an upload is a manifest (JSON)", loc=("body",), kind="not_json"
        )
    arrived = request.scope.get(RECEIVED_AT)
    return body, arrived if isinstance(arrived, datetime) else utcnow()


@router.put(
    "/auctions/{auction_id}/rounds/{round}/models/{model_id}",
    operation_id="upload_round_model",
    response_class=Response,
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Manifest"}}},
        }
    },
    responses={
        200: {
            "model": UploadPublic,
            "description": "Accepted, refused or held by the re-screening",
        },
        **responses(401, 403, 404, 409, 410, 413, 422, 503),
    },
)
async def upload_round_model(
    auction_id: AuctionIdPath,
    round_number: RoundPath,
    model_id: ModelIdPath,
    body: Annotated[tuple[bytes, datetime], Depends(_upload_body)],
    token: ParticipantTokenDep,
    database: DatabaseDep,
    screening: ScreeningDep,
    runner: AuctionRunnerDep,
    settings: SettingsDep,
    arrivals: ArrivalsDep,
    http: Request,
) -> Response:
    """Upload the patron's fine-tuned manifest for this round (participant token). It is
    re-screened: accepted, it becomes the participant's next version and bids from the next
    iteration; refused (or held for an inspector, ``SRD_REVIEW_MARGIN``), the reasons are
    returned and the previous version bids on. Wrong round
    → 409 naming the current one; closed or past the deadline → 410 (recorded as late)."""
    content, arrived = body
    address = http.client.host if http.client is not None else None
    journaled = await client_limits(http.scope).real_token(http.scope, token)
    request = rounds.UploadRequest(
        auction_id, round_number, model_id, token, content, arrived, address, journaled
    )
    answer = await rounds.upload(
        database,
        screening,
        runner.submit,
        request,
        margin=settings.review_margin,
        arrivals=arrivals,
    )
    return Response(answer, media_type="application/json")


def _share_taken(auction_id: int, what: str) -> str:
    """Why a patron's token was refused one more of the patrons' slots of an auction."""
    return (
        f"this participant holds {patron_shares.MAX_PER_PATRON} of the patrons' {what} of "
        f"auction {auction_id} already, its share (everyone's share is full)"
    )


def _bearer(header: str | None) -> str | None:
    """The credentials of an ``Authorization: Bearer <token>`` header, if it has them."""
    scheme, _, credentials = (header or "").partition(" ")
    credentials = credentials.strip()
    return credentials if scheme.lower() == "bearer" and credentials else None


async def _deny(websocket: WebSocket, error: RequestError) -> None:
    """Refuse a handshake with the common error body."""
    await websocket.send_denial_response(problem_response(error))


@router.websocket("/auctions/{auction_id}/rounds/socket")
async def round_socket(
    websocket: WebSocket,
    auction_id: AuctionIdPath,
    watcher: RoundsDep,
    sockets: RoundSocketsDep,
    patrons: PatronsDep,
    database: DatabaseDep,
    screening: ScreeningDep,
    runner: AuctionRunnerDep,
    settings: SettingsDep,
    arrivals: ArrivalsDep,
) -> None:
    """The auction's remote rounds over one WebSocket (``server.auctions.sockets``):
    every round pushed as it opens, uploads answered as the PUT answers them. Uploads need
    the handshake's ``Authorization: Bearer <participant token>``."""
    # It takes no query parameter: a misspelt option is refused, not silently ignored.
    unknown = unknown_parameter(websocket, frozenset())
    if unknown is not None:
        await _deny(websocket, unknown)
        return
    header = websocket.headers.get("authorization")
    token = _bearer(header)
    if header is not None and token is None:  # a client's mistake, told now, not at an upload
        await _deny(
            websocket,
            api_error(
                401,
                "the Authorization header is not 'Bearer <participant token>' (leave it out to "
                "watch the rounds without uploading)",
                loc=("header", "Authorization"),
                kind="bad_authorization",
            ),
        )
        return
    limits = client_limits(websocket.scope)

    async def is_patron() -> bool:
        return await patrons.is_patron(auction_id, token)

    patron, release_claim = False, None
    try:
        try:
            sockets.reserve(patron=False)  # the others' share while it has room: no read
        except SocketLimitError:
            release_claim = await patrons.claim(auction_id, token)
            if release_claim is None:
                if await patrons.is_patron(auction_id, token):
                    raise SocketLimitError(_share_taken(auction_id, "round sockets")) from None
                raise
            patron = True
            sockets.reserve(patron=True)
    except SocketLimitError as exc:
        if release_claim is not None:
            release_claim()
        await _deny(
            websocket,
            api_error(
                503,
                f"{exc}; retry in {RETRY_AFTER_S} s",
                loc=("server",),
                kind="too_many_sockets",
                headers={"Retry-After": str(RETRY_AFTER_S)},
            ),
        )
        return
    try:
        first = await watcher.published(auction_id, wait_s=0.0, after=0)
        if first is None:
            await _deny(websocket, not_found(auction_id))
            return
        await websocket.accept()

        async def upload(round_number: int, model_id: int, body: bytes, arrived: datetime) -> bytes:
            if token is None:
                raise api_error(
                    401,
                    "uploads need the participant's token: 'Authorization: Bearer <token>' "
                    "in the socket's handshake",
                    loc=("header", "Authorization"),
                    kind="missing_token",
                )
            address = websocket.client.host if websocket.client is not None else None
            journaled = await limits.real_token(websocket.scope, token)
            request = rounds.UploadRequest(
                auction_id, round_number, model_id, token, body, arrived, address, journaled
            )
            release = await limits.hold(websocket.scope, limits.uploads)  # as a PUT's: 429
            try:
                return await rounds.upload(
                    database,
                    screening,
                    runner.submit,
                    request,
                    margin=settings.review_margin,
                    arrivals=arrivals,
                )
            finally:
                release()

        def allowance(size: int) -> RequestError | None:
            return limits.message(websocket.scope, size)

        await sockets.serve(websocket, auction_id, first, upload, patron, is_patron, allowance)
    finally:
        sockets.release(patron)
        if release_claim is not None:
            release_claim()


@router.websocket("/{path:path}")
async def no_socket_here(websocket: WebSocket, path: str) -> None:
    """Any other path asked for a WebSocket: 404 in the common body (instead of the
    framework's bare 403). The round socket is the only one."""
    await _deny(
        websocket,
        api_error(
            404,
            f"no WebSocket at /{path}: the round socket is /auctions/{{id}}/rounds/socket",
            loc=("path",),
            kind="not_found",
        ),
    )
