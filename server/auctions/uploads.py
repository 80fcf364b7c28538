"""Remote fine-tuning rounds: the newest round of an auction (long poll), and a patron's
upload for a round, checked, stored, re-screened and answered.

An upload's identity and round come from its path and its bearer token only: the token must be
the participant's of ``model_id``, ``model_id`` one of the auction's patrons (as listed in its
``model_ids``), asked in that round; the manifest must name the same participant and may change
weights and biases only. One upload per round per patron: the same bytes again get the same
answer, other bytes 409.

The API owns every write of an upload: it stores the upload, pending, as soon as its body is
read and checked (so the deadline is judged at arrival, whatever the screener's backlog), asks
the screener pool for a verdict and records it; the verdict that judges the last asked patron's
upload closes the round in the same transaction, and the auction's next step is due at once. An
upload whose verdict was never recorded (the screener down, the server killed) counts all the
same: a repeat of its bytes asks again, and the step that closes the round judges whatever is
still pending (a request still waiting for a hung screener then answers with the step's
verdict); in a round a cancel or a failure closed, the API judges it after the cancel and at
its next start (``judge_left_pending``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import hashlib
import json
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Any, TypeVar

from sqlalchemy import Connection
from sqlalchemy.exc import IntegrityError
from starlette.concurrency import run_in_threadpool

from agents.manifest import Manifest, ManifestError, parse_manifest, parse_manifest_json
from screener import Verdict
from server.api.errors import api_error, error_item, validation_error
from server.api.security import require_participant
from server.auctions.arrivals import Arrivals
from server.auctions.service import not_found
from server.live.rounds import RoundWatcher, TooManyWaitersError
from server.screening.pool import ScreenerUnavailableError, ScreeningService
from server.store import crud
from server.store.db import (
    Database,
    DatabaseUnavailableError,
    JSONText,
    WriteLockBusyError,
    is_database_outage,
)
from server.store.status import ANSWERED, AUCTION_ENDED, RoundStatus
from server.store.tables import utcnow
from server.submissions import quotas
from sim.market.design import design_changes

T = TypeVar("T")
log = logging.getLogger("srd.rounds")

RETRY_AFTER_S = 1
"""Retry-After of a round request refused because too many wait."""
JUDGED_GRACE_S = 1.0
"""How long after the round's deadline an upload still waiting for the screener first looks
whether the step that closes the round judged it (it judges what is still pending)."""
JUDGED_RECHECK_S = 2.0
"""Then how often it looks again, until the screener answers or gives up."""
AT_ONCE_TRIES = 8
"""An upload's write on SQLite tries the write lock at once up to this many times, each time
after the thread of this process that held it let go, before it waits for it in a thread."""


async def current_round(
    watcher: RoundWatcher,
    auction_id: int,
    *,
    wait_s: float,
    after: int,
    claim: Callable[[], Awaitable[Callable[[], None] | None]],
) -> bytes:
    """The JSON of the auction's newest round, once a round above ``after`` is open or the
    auction has ended, or after ``wait_s`` (404 for no auction). It waits in everyone's share
    while that has room, else, for a patron (``claim``: its token is looked up only then, and
    holds at most ``MAX_PER_PATRON`` of the patrons' slots), in the patrons' own; 503 when its
    share is full (``claim`` raises TooManyWaitersError to say why, e.g. a patron holding its
    slots already)."""
    try:
        try:
            body = await watcher.current(auction_id, wait_s=wait_s, after=after)
        except TooManyWaitersError:
            release = await claim()
            if release is None:
                raise
            try:
                body = await watcher.current(auction_id, wait_s=wait_s, after=after, patron=True)
            finally:
                release()
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
    if target.auction_status in AUCTION_ENDED:  # no round will open again
        last = "" if target.newest_round is None else f": its last round was {target.newest_round}"
        return f"the auction has ended ({target.auction_status}){last}"
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
        errors = exc.errors
        if any(e["path"] == "$" for e in errors):  # JSON the fast parser cannot say where
            errors = _located(body) or errors  # (a lone surrogate escape): read it as /submit
        raise validation_error(
            error_item(e["message"], loc=_body_loc(e["path"]), kind=e.get("type", "manifest"))
            for e in errors  # the schema's type, as POST /submit names it
        ) from exc


def _body_loc(path: str) -> tuple[str, ...]:
    """A manifest error's path as a body location: ``$`` (the manifest as a whole, such as a
    body that is not an object) is the body itself, as ``POST /submit`` says it."""
    return ("body",) if path == "$" else ("body", *path.split("."))


def _located(body: bytes) -> list[dict[str, str]]:
    """The problems of a body the JSON reader refused as a whole, each at its field, as
    ``POST /submit`` reads a manifest (Python's JSON reader, then the schema); [] if that
    finds none."""
    try:
        parse_manifest(json.loads(body))
    except ManifestError as exc:
        return exc.errors
    except (ValueError, RecursionError):
        return []
    return []


def _target(
    connection: Connection, auction_id: int, model_id: int, round_number: int
) -> crud.UploadTarget:
    """What the upload's path names: the patron, its participant, the round (404 for an
    unknown auction or model)."""
    target = crud.upload_target(
        connection, auction_id=auction_id, model_id=model_id, round_number=round_number
    )
    if not isinstance(target, crud.UploadLookupError):
        return target
    if target.field == "auction_id":
        raise not_found(auction_id) from target
    raise api_error(
        404, f"model {model_id} does not exist", loc=("path", "model_id"), kind="not_found"
    ) from target


def _check_patron(
    target: crud.UploadTarget, token: str, *, auction_id: int, model_id: int, round_number: int
) -> int:
    """The token is the patron's participant's, the model a patron of this remote auction,
    and the round has opened: its id."""
    require_participant(token, target.token_hash, target.participant)
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
            f"auction {auction_id} has no remote fine-tuning rounds (its fine_tune_mode is "
            "server: the market fine-tunes its patrons itself, if at all)",
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


def _record(
    connection: Connection,
    *,
    answer_id: int,
    round_id: int,
    verdict: Verdict,
    margin: float,
    participant: str,
    address: str | None,
) -> tuple[bytes, bool]:
    """Record a pending upload's verdict; its answer, and whether it closed the round (every
    asked patron judged: the auction is due). Its verdict counts for the participant's
    cooldown as a ``/submit``'s does (``quotas.record_round_upload``), once: a retry of the
    same body judged by another request or replica meanwhile takes its answer uncounted."""
    now = utcnow()
    recorded = crud.record_verdict(
        connection, answer_id=answer_id, verdict=verdict, margin=margin, now=now
    )
    if recorded.judged:
        quotas.record_round_upload(
            connection,
            participant=participant,
            address=address,
            accepted=recorded.accepted,
            now=now,
        )
    return recorded.answer, crud.close_when_answered(connection, round_id=round_id, now=now)


def _close(connection: Connection, *, round_id: int) -> bool:
    return crud.close_when_answered(connection, round_id=round_id, now=utcnow())


async def _write(database: Database, work: Callable[[Connection], T]) -> T:
    """``work(connection)`` in one write transaction, committed unless it raises.

    On SQLite it runs at once on the event loop when the write lock is free, as it mostly is
    (the other writers' transactions are short): an upload's two transactions, a fraction of a
    millisecond each, then take no hop to a thread, whose hand-offs of the GIL cost more than
    the transactions themselves under load. If a thread of this process holds the lock, the
    upload waits (on the event loop, stalling nobody) for it to let go and tries again; if
    another process holds it, it runs in the thread pool, where waiting stalls nobody; so does
    every write on PostgreSQL, whose statements wait on the network."""
    if database.writes_at_once:
        for _ in range(AT_ONCE_TRIES):
            try:
                with database.transaction_at_once() as connection:
                    return work(connection)
            except WriteLockBusyError as busy:
                if not busy.in_process:
                    break
            await _released(database)
    return await run_in_threadpool(_write_in_thread, database, work)


async def _released(database: Database) -> None:
    """Until the thread of this process that holds SQLite's write lock lets go of it."""
    loop = asyncio.get_running_loop()
    released = loop.create_future()

    def resolve() -> None:
        if not released.done():
            released.set_result(None)

    def tell() -> None:  # from the releasing thread
        with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
            loop.call_soon_threadsafe(resolve)

    database.on_write_release(tell)
    await released


def _write_in_thread(database: Database, work: Callable[[Connection], T]) -> T:
    with database.transaction(write=True) as connection:
        return work(connection)


@dataclass(frozen=True)
class UploadRequest:
    """One upload as it reached the API: what its path names, who sent it, its body and when
    it arrived (the deadline is judged at that moment)."""

    auction_id: int
    round_number: int
    model_id: int
    token: str
    body: bytes
    arrived: datetime
    address: str | None = None
    """The client's address (None in process): a refused or held upload counts against it."""
    journaled: bool = True
    """Whether its arrival is journaled: its token is real, or the database could not say
    (made-up ones, which the checks refuse anyway, would fill the journal for everyone)."""


def _arrive(
    connection: Connection,
    *,
    manifest: Manifest,
    data: dict[str, Any],
    request: UploadRequest,
    digest: str,
    giving_back: bool,
) -> tuple[crud.Stored, int, str | None, datetime | None]:
    """The upload's checks against what its path names and its store, in one transaction (a
    refused upload stores nothing, but a late one is recorded as late): what was stored (or
    refused), the round's id, the new manifest's JSON (None: the current weights) and the
    round's deadline. While this process has not yet given the open rounds back the time of
    an outage it met (``giving_back``: its lease runner does at its next pass), an upload that
    would be late is answered as in the outage (503, its arrival remembered for its retry)."""
    auction_id, round_number, model_id = request.auction_id, request.round_number, request.model_id
    target = _target(connection, auction_id, model_id, round_number)
    round_id = _check_patron(
        target, request.token, auction_id=auction_id, model_id=model_id, round_number=round_number
    )
    if target.answer_outcome in ANSWERED and target.answer_sha256 != digest:
        raise api_error(
            409,
            f"this patron already answered round {round_number} with another body: one "
            "upload per round",
            loc=("path", "round"),
            kind="already_answered",
        )
    if target.position not in target.asked and target.answer_outcome is None:
        raise api_error(
            409,
            f"model {model_id} is not asked in round {round_number}: it left the auction "
            "(bought or quit) before it",
            loc=("path", "model_id"),
            kind="not_asked",
        )
    late = target.round_status != RoundStatus.OPEN or (
        target.deadline is not None and target.deadline <= request.arrived
    )
    if late and giving_back and target.round_status == RoundStatus.OPEN:
        raise DatabaseUnavailableError(
            "the database was unavailable: the round's deadline is being pushed back by the "
            "outage; send the same body again"
        )
    if not late and target.answer_outcome not in ANSWERED:
        problems = _body_problems(data, target)
        if problems:
            raise validation_error(problems)
    assert target.position is not None
    manifest_json = None if data == target.current_manifest else manifest.model_dump_json()
    stored = crud.store_upload(
        connection,
        upload=crud.UploadIn(
            round_number=round_number,
            round_id=round_id,
            position=target.position,
            current_id=target.current_id,
            current_version=target.current_version,
            body_sha256=digest,
            bytes_in=len(request.body),
            arrived=request.arrived,
            manifest=None if manifest_json is None else JSONText(manifest_json),
        ),
        target=target,
    )
    return stored, round_id, manifest_json, target.deadline


async def upload(
    database: Database,
    screening: ScreeningService,
    wake: Callable[[int], None],
    request: UploadRequest,
    *,
    margin: float,
    arrivals: Arrivals,
) -> bytes:
    """Check an upload (see the module docstring), store it, re-screen it and record its
    verdict; the answer's JSON. Wrong round → 409 naming the current one; closed, or past the
    deadline at its arrival → 410 (recorded as late): ``request.arrived``, or the first arrival
    of the same bytes that had no answer (a database outage refused it, or the server was
    killed before it was stored: ``arrivals``, which journals each arrival before the store).
    ``wake(auction_id)`` is told when the auction's next step became due."""
    manifest = _manifest(request.body)
    data = manifest.model_dump(mode="json")
    digest = hashlib.sha256(request.body).hexdigest()
    key = arrivals.key(
        request.auction_id, request.round_number, request.model_id, request.token, digest
    )
    request = dataclasses.replace(request, arrived=arrivals.first(key, request.arrived))
    if request.journaled:
        arrivals.arrived(key, request.arrived)
    arrive = functools.partial(
        _arrive,
        manifest=manifest,
        data=data,
        request=request,
        digest=digest,
        giving_back=database.outage_began() is not None,
    )
    try:
        try:
            stored, round_id, manifest_json, deadline = await _write(database, arrive)
        except IntegrityError:  # the same patron's answer, stored meanwhile by a concurrent one
            stored, round_id, manifest_json, deadline = await _write(database, arrive)  # a repeat
    except Exception as exc:
        if is_database_outage(exc):  # its retry is judged by this arrival
            arrivals.remember(key, request.arrived)
            database.note_outage(exc)  # no step closes its round before the retry can come
        else:  # a refusal (wrong token, patron or round; malformed): its answer
            arrivals.answered(key, journaled=request.journaled)
        raise
    arrivals.answered(key, journaled=request.journaled)
    if stored.refusal is not None:
        status, message, kind = stored.refusal
        raise api_error(status, message, loc=("path", "round"), kind=kind)
    if stored.answer is not None:  # a repeat, or the current weights: answered at once
        if manifest_json is None and await _write(
            database, functools.partial(_close, round_id=round_id)
        ):
            wake(request.auction_id)
        return stored.answer
    answer_id = stored.answer_id
    assert answer_id is not None
    asked = screening.verdict(manifest, at_the_door=False, manifest_json=manifest_json)
    try:
        verdict = await _verdict_or_answer(database, asked, answer_id, deadline)
    except ScreenerUnavailableError as exc:
        raise api_error(
            503,
            f"{exc}; the upload is stored in time: send the same body again for its verdict",
            loc=("body",),
            kind="screener_unavailable",
            headers={"Retry-After": str(RETRY_AFTER_S)},
        ) from exc
    if isinstance(verdict, bytes):  # the step closing the round judged it meanwhile
        return verdict
    record = functools.partial(
        _record,
        answer_id=answer_id,
        round_id=round_id,
        verdict=verdict,
        margin=margin,
        participant=manifest.participant,
        address=request.address,
    )
    answer, due = await _write(database, record)
    if due:
        wake(request.auction_id)
    return answer


async def judge_left_pending(
    database: Database,
    screening: ScreeningService,
    *,
    margin: float,
    auction_id: int | None = None,
) -> int:
    """Judge the uploads that closed rounds left pending, as their requests would have (each
    verdict recorded, an accepted upload its participant's new version); the number judged.
    A cancel or a failure closes a round whatever its uploads, and one whose request no longer
    waits for its verdict (the server was killed, or the screener was down and no retry of the
    same body came) stayed pending for ever. It came in time, so it counts. Run at start and
    after a cancel (of that auction); one that fails (the screener or the database unavailable)
    is logged, and the rest are left to a retry of their bodies or the next start."""
    try:
        left = await run_in_threadpool(_left_in_thread, database, auction_id)
        for upload in left:
            manifest = parse_manifest(upload.manifest)
            verdict = await screening.verdict(manifest, at_the_door=False)
            record = functools.partial(
                _record,
                answer_id=upload.answer_id,
                round_id=upload.round_id,
                verdict=verdict,
                margin=margin,
                participant=manifest.participant,
                address=None,
            )
            await _write(database, record)
    except Exception as exc:
        log.warning("uploads left pending by closed rounds: not judged now: %s", exc)
        return 0
    if left:
        log.info("%d uploads left pending by closed rounds judged", len(left))
    return len(left)


def _left_in_thread(database: Database, auction_id: int | None) -> list[crud.PendingUpload]:
    with database.session(write=False) as session:
        return crud.left_pending(session, auction_id=auction_id)


async def _verdict_or_answer(
    database: Database, asked: Awaitable[Verdict], answer_id: int, deadline: datetime | None
) -> Verdict | bytes:
    """The screener's verdict, or the answer the step that closes the round recorded if it
    judged the upload first (the screener hung past the deadline: the step judges what is
    still pending), so the agent hears it within seconds of the deadline instead of when the
    screener gives up."""
    verdict = asyncio.ensure_future(asked)
    try:
        timeout = None  # no deadline: the screener's own timeout bounds the wait
        if deadline is not None:
            timeout = max(0.0, (deadline - utcnow()).total_seconds()) + JUDGED_GRACE_S
        while True:
            done, _ = await asyncio.wait({verdict}, timeout=timeout)
            if done:
                return verdict.result()
            answer = await run_in_threadpool(_read_in_thread, database, answer_id)
            if answer is not None:
                return answer
            timeout = JUDGED_RECHECK_S
    finally:
        verdict.cancel()  # done already, or no longer wanted


def _read_in_thread(database: Database, answer_id: int) -> bytes | None:
    with database.transaction(write=False) as connection:
        return crud.judged_answer(connection, answer_id=answer_id)
