"""Remote fine-tuning rounds: the newest round of an auction (long poll), and a patron's
upload for a round, checked, re-screened and stored.

An upload's identity and round come from its path and its bearer token only: the token must be
the participant's of ``model_id``, ``model_id`` one of the auction's patrons (as listed in its
``model_ids``), asked in that round; the manifest must name the same participant and may change
weights and biases only. One upload per round per patron: the same bytes again get the same
answer, other bytes 409.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any

from sqlalchemy.exc import OperationalError

from agents.manifest import Manifest, ManifestError, parse_manifest_json
from server import crud
from server.db import DatabaseUnavailableError, JSONText
from server.errors import (
    RequestError,
    api_error,
    database_unavailable,
    error_item,
    validation_error,
)
from server.grouping import StoppingError
from server.models import utcnow
from server.remote_rounds import (
    Answered,
    RoundWatcher,
    TooManyWaitersError,
    UploadLookup,
    UploadOutcome,
    UploadRequest,
    answer_bytes,
)
from server.screening import ScreenerUnavailableError, ScreeningService
from server.security import token_matches
from server.services.auctions import not_found
from server.status import ANSWERED, RoundStatus
from sim.market.design import design, design_changes

RETRY_AFTER_S = 1
"""Retry-After of a round request refused because too many wait."""


async def current_round(
    watcher: RoundWatcher, auction_id: int, *, wait_s: float, after: int
) -> bytes:
    """The JSON of the auction's newest round, once a round above ``after`` is open or the
    auction has ended, or after ``wait_s`` (404 for no auction, 503 when too many wait)."""
    try:
        body = await watcher.current(auction_id, wait_s=wait_s, after=after)
    except TooManyWaitersError as exc:
        raise api_error(
            503,
            f"{exc}; retry in {RETRY_AFTER_S} s",
            loc=("query", "wait"),
            kind="too_many_waiters",
            headers={"Retry-After": str(RETRY_AFTER_S)},
        ) from exc
    if body is None:
        raise not_found(auction_id)
    return body


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


def _manifest(body: bytes) -> Manifest:
    """The upload's manifest, parsed strictly (422 naming each problem)."""
    try:
        return parse_manifest_json(body)
    except ManifestError as exc:
        raise validation_error(
            error_item(e["message"], loc=("body", *e["path"].split(".")), kind="manifest")
            for e in exc.errors
        ) from exc


async def _target(
    lookup: UploadLookup, auction_id: int, model_id: int, round_number: int
) -> crud.UploadTarget:
    """What the upload's path names: the patron, its participant, the round (404 for an
    unknown auction or model)."""
    try:
        target = await lookup.get((auction_id, model_id, round_number))
    except (OperationalError, DatabaseUnavailableError) as exc:
        raise database_unavailable(exc) from exc
    except StoppingError as exc:
        raise api_error(503, "the server is stopping", loc=("body",), kind="stopping") from exc
    except crud.UploadLookupError as exc:
        if exc.field == "auction_id":
            raise not_found(auction_id) from exc
        raise api_error(
            404, f"model {model_id} does not exist", loc=("path", "model_id"), kind="not_found"
        ) from exc
    return target


def _check_patron(
    target: crud.UploadTarget, token: str, *, auction_id: int, model_id: int, round_number: int
) -> int:
    """The token is the patron's participant's, the model a patron of this remote auction,
    and the round has opened: its id."""
    if not token_matches(token, target.token_hash):
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
    return target.round_id


async def upload(
    lookup: UploadLookup,
    screening: ScreeningService,
    *,
    auction_id: int,
    round_number: int,
    model_id: int,
    token: str,
    body: bytes,
) -> bytes:
    """Check an upload (see the module docstring), re-screen it and store its answer; the
    answer's JSON. Wrong round → 409 naming the current one; closed or past the deadline →
    410 (recorded as late)."""
    manifest = _manifest(body)
    target = await _target(lookup, auction_id, model_id, round_number)
    round_id = _check_patron(
        target, token, auction_id=auction_id, model_id=model_id, round_number=round_number
    )
    digest = hashlib.sha256(body).hexdigest()
    if target.answer_outcome in ANSWERED:
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
        round_id=round_id,
        position=target.position,
        participant_id=target.participant_id,
        current_id=target.current_id,
        current_version=target.current_version,
        auction_id=auction_id,
        body_sha256=digest,
        bytes_in=len(body),
    )
    if target.round_status != RoundStatus.OPEN or (
        target.deadline is not None and target.deadline <= utcnow()
    ):
        return _answered(await _store(screening, late))
    data = manifest.model_dump(mode="json")
    if target.current_design is None or design(manifest) != target.current_design:
        problems = _body_problems(data, target)
        if problems:
            raise validation_error(problems)
    if data == target.current_manifest:
        request = dataclasses.replace(late, kind="unchanged")
    else:  # re-screened and stored in the screening process, as it is
        encoded = JSONText(manifest.model_dump_json())
        request = dataclasses.replace(late, kind="version", manifest=encoded)
    outcome = await _store(screening, request)
    if isinstance(outcome, Answered):
        lookup.answered((auction_id, model_id, round_number), digest, outcome.body)
    return _answered(outcome)


async def _store(screening: ScreeningService, request: UploadRequest) -> UploadOutcome:
    """The upload stored (a new version re-screened first) by the screening process."""
    try:
        return await screening.upload(request)
    except ScreenerUnavailableError as exc:
        raise api_error(503, str(exc), loc=("body",), kind="screener_unavailable") from exc


def _answered(outcome: UploadOutcome) -> bytes:
    if isinstance(outcome, Answered):
        return outcome.body
    if outcome.kind == "db_unavailable":
        raise database_unavailable(outcome.msg)
    raise RequestError(
        outcome.status, [error_item(outcome.msg, loc=outcome.loc, kind=outcome.kind)]
    )
