"""Remote fine-tuning rounds: ``GET /auctions/{id}/rounds/current`` publishes the newest round
(long poll with ``?wait=``), ``PUT /auctions/{id}/rounds/{round}/models/{model_id}`` takes a
patron's fine-tuned manifest, re-screens it and stores it as a new version.

An upload's identity and round come from its path and its bearer token only: the token must be
the participant's of ``model_id``, ``model_id`` one of the auction's patrons (as listed in its
``model_ids``), asked in that round; the manifest must name the same participant and may change
weights and biases only. One upload per round per patron: the same bytes again get the same
answer, other bytes 409.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request, Response
from sqlalchemy.exc import OperationalError

from agents.manifest import ManifestError, parse_manifest_json
from server import crud
from server.errors import api_error, error_item, responses, validation_error
from server.models import utcnow
from server.remote_rounds import (
    MAX_WAIT_S,
    Answered,
    RoundWatcher,
    TooManyWaitersError,
    UploadLookup,
    UploadOutcome,
    UploadRequest,
    UploadWriter,
    answer_bytes,
)
from server.schemas import (
    MAX_FINE_TUNE_ROUNDS,
    AuctionIdPath,
    ModelIdPath,
    RoundPublic,
    UploadPublic,
)
from server.screening import ScreenerUnavailableError, ScreeningService
from server.security import BearerDep, token_matches
from sim.market import design_changes

router = APIRouter(tags=["rounds"])

UPLOAD_MAX_BYTES = 65_536
"""Largest upload body (a manifest is about 5 KB)."""
RETRY_AFTER_S = 1
"""Retry-After of a round request refused because too many wait."""

RoundPath = Annotated[
    int,
    Path(
        alias="round",
        ge=1,
        le=MAX_FINE_TUNE_ROUNDS,
        description="A fine-tuning round (1 follows iteration 0, 2 iteration 1, ...).",
    ),
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
    auction_id: AuctionIdPath,
    request: Request,
    wait: Annotated[
        float,
        Query(
            ge=0,
            le=MAX_WAIT_S,
            allow_inf_nan=False,
            description="Seconds to wait for a round above ``after`` to open (or the end).",
        ),
    ] = 0.0,
    after: Annotated[
        int,
        Query(ge=0, le=MAX_FINE_TUNE_ROUNDS, description="The last round the client handled."),
    ] = 0,
) -> Response:
    """The auction's newest fine-tuning round: status open | closed | none, its deadline
    (UTC) and seconds left; while open the item rows, the seeds and the patrons asked. With
    ``wait`` the answer comes as soon as a round numbered above ``after`` is open or the
    auction has ended, and at the latest after ``wait`` seconds."""
    watcher: RoundWatcher = request.app.state.rounds
    try:
        body = await watcher.current(auction_id, wait_s=wait, after=after)
    except TooManyWaitersError as exc:
        raise api_error(
            503,
            f"{exc}; retry in {RETRY_AFTER_S} s",
            loc=("query", "wait"),
            kind="too_many_waiters",
            headers={"Retry-After": str(RETRY_AFTER_S)},
        ) from exc
    if body is None:
        raise _no_auction(auction_id)
    return Response(body, media_type="application/json")


def _no_auction(auction_id: int) -> Exception:
    return api_error(
        404, f"auction {auction_id} does not exist", loc=("path", "auction_id"), kind="not_found"
    )


def _round_state(target: crud.UploadTarget) -> str:
    if target.newest_round is None:
        return "no round has opened yet"
    return f"the current round is {target.newest_round} ({target.newest_status})"


def _body_problems(data: dict[str, Any], target: crud.UploadTarget) -> list[dict[str, Any]]:
    """What the manifest (JSON form) changes beyond weights and biases, as 422 items naming
    each field."""
    problems = []
    for path, message in design_changes(target.current_manifest, data):
        if path == "participant":
            message = (
                f"must be the patron's participant {target.participant!r} (who uploads is "
                "the path and the token, not the body)"
            )
        problems.append(error_item(message, loc=("body", *path.split(".")), kind="frozen"))
    return problems


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
        200: {"model": UploadPublic, "description": "Accepted or refused by the re-screening"},
        **responses(401, 403, 404, 409, 410, 413, 422, 503),
    },
)
async def upload_round_model(
    auction_id: AuctionIdPath,
    round_number: RoundPath,
    model_id: ModelIdPath,
    credentials: BearerDep,
    request: Request,
) -> Response:
    """Upload the patron's fine-tuned manifest for this round (participant token). It is
    re-screened: accepted, it becomes the participant's next version and bids from the next
    iteration; refused, the reasons are returned and the previous version bids on. Wrong round
    → 409 naming the current one; closed or past the deadline → 410 (recorded as late)."""
    body = await request.body()
    if len(body) > UPLOAD_MAX_BYTES:
        raise api_error(
            413,
            f"an upload is at most {UPLOAD_MAX_BYTES} bytes",
            loc=("header", "Content-Length"),
            kind="body_size",
        )
    if credentials is None:
        raise api_error(
            401,
            "uploads need the participant's token: 'Authorization: Bearer <token>'",
            loc=("header", "Authorization"),
            kind="missing_token",
        )
    try:
        manifest = parse_manifest_json(body)
    except ManifestError as exc:
        raise validation_error(
            error_item(e["message"], loc=("body", *e["path"].split(".")), kind="manifest")
            for e in exc.errors
        ) from exc
    lookup: UploadLookup = request.app.state.upload_lookup
    try:
        target = await lookup.get((auction_id, model_id, round_number))
    except OperationalError as exc:
        raise api_error(503, f"the database is unavailable: {exc}", kind="db_unavailable") from exc
    except crud.UploadLookupError as exc:
        if exc.field == "auction_id":
            raise _no_auction(auction_id) from exc
        raise api_error(
            404, f"model {model_id} does not exist", loc=("path", "model_id"), kind="not_found"
        ) from exc
    if not token_matches(credentials.credentials, target.token_hash):
        raise api_error(
            403,
            f"the bearer token is not the token of participant {target.participant!r}",
            loc=("header", "Authorization"),
            kind="bad_token",
        )
    if target.position is None:
        raise api_error(
            404,
            f"model {model_id} is not a patron of auction {auction_id} (patrons are named by "
            "the ids in its model_ids)",
            loc=("path", "model_id"),
            kind="not_a_patron",
        )
    if target.fine_tune_mode != "remote":
        raise api_error(
            409,
            f"auction {auction_id} fine-tunes in the server: it has no remote rounds",
            loc=("path", "auction_id"),
            kind="not_remote",
        )
    if target.round_id is None:
        raise api_error(
            409,
            f"round {round_number} has not opened: {_round_state(target)}",
            loc=("path", "round"),
            kind="wrong_round",
        )
    digest = hashlib.sha256(body).hexdigest()
    if target.answer_outcome in ("accepted", "refused"):
        if target.answer_sha256 == digest and target.answer is not None:
            return _answered(Answered(answer_bytes(target.answer)))
        raise api_error(
            409,
            f"this patron already answered round {round_number} with another body: one "
            "upload per round",
            loc=("path", "round"),
            kind="already_answered",
        )
    if target.position not in target.asked:
        raise api_error(
            409,
            f"model {model_id} is not asked in round {round_number}: it left the auction "
            "(bought or quit) before it",
            loc=("path", "model_id"),
            kind="not_asked",
        )
    late = UploadRequest(
        kind="late",
        round_number=round_number,
        round_id=target.round_id,
        position=target.position,
        participant_id=target.participant_id,
        current_id=target.current_id,
        current_version=target.current_version,
        auction_id=auction_id,
        body_sha256=digest,
        bytes_in=len(body),
    )
    writer: UploadWriter = request.app.state.uploads
    if target.round_status != "open" or (
        target.deadline is not None and target.deadline <= utcnow()
    ):
        return _answered(await writer.store(late))
    data = manifest.model_dump(mode="json")
    problems = _body_problems(data, target)
    if problems:
        raise validation_error(problems)
    if data == target.current_manifest:
        return _answered(await writer.store(dataclasses.replace(late, kind="unchanged")))
    screening: ScreeningService = request.app.state.screening
    try:
        verdict = await screening.verdict(manifest, at_the_door=False)
    except ScreenerUnavailableError as exc:
        raise api_error(503, str(exc), loc=("body",), kind="screener_unavailable") from exc
    return _answered(
        await writer.store(
            dataclasses.replace(late, kind="version", manifest=data, verdict=verdict)
        )
    )


def _answered(outcome: UploadOutcome) -> Response:
    if isinstance(outcome, Answered):
        return Response(outcome.body, media_type="application/json")
    raise api_error(outcome.status, outcome.msg, loc=outcome.loc, kind=outcome.kind)
