"""The API's side of remote fine-tuning rounds: the round watcher (long polls) and the upload
writer (group commits).

``RoundWatcher`` answers ``GET /auctions/{id}/rounds/current``. However many agents wait on an
auction, this process reads that auction's round from the database at most once per
``WATCH_POLL_S``: one asyncio task per watched auction polls while anyone waits and wakes every
waiter when a round opens or the auction ends, and requests that do not wait share the latest
snapshot while it is younger than that (the snapshots of ``MAX_WATCHED`` auctions are kept).
The answer body of a round is built once (its 64 × 8 rows serialised once) and shared by all
its waiters; only ``seconds_left`` is written per answer. Waiters are bounded (``MAX_WAITERS``
per process; beyond that 503 with Retry-After). The bytes of the answers that carry a round are
counted in memory and added to the round's ``bytes_published`` by the upload writer, which
flushes them at most every ``FLUSH_S``.

``UploadWriter`` stores the decided uploads of ``PUT .../rounds/{round}/models/{model_id}`` in
group commits (as ``server.submissions`` does for ``/submit``): one thread takes every upload
queued since its last pass and writes them in ONE transaction, re-checking there, against the
database, that each round is still open and before its deadline (a round closed meanwhile
makes the upload late) and that the patron has not answered the round yet. On PostgreSQL the
rounds are read ``FOR SHARE``: the worker's closing ``UPDATE`` waits for the uploads in flight,
and the uploads that come after it see the round closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import queue
import threading
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, Literal

from sqlalchemy import insert, select, update
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from screener import Verdict
from server import crud
from server.db import Database
from server.models import FineTuneAnswer, FineTuneRound, Participant, utcnow
from server.status import ANSWERED, AUCTION_UNFINISHED, AnswerOutcome, RoundStatus

log = logging.getLogger("srd.rounds")

WATCH_POLL_S = 0.004
"""How often a watched auction's round is read while agents wait on it."""
MAX_WAIT_S = 30.0
"""Longest ``?wait=`` a round request may ask for."""
MAX_WAITERS = 2048
"""Round requests waiting at once in one API process (beyond: 503)."""
MAX_WATCHED = 256
"""Auctions whose latest snapshot this process keeps (the idle ones beyond are forgotten)."""
FLUSH_S = 0.2
"""Published-bytes counters are written at least this often while they grow."""
MAX_GROUP = 64
"""Uploads per transaction, at most."""
STOP_GRACE_S = 10.0

PublishedStatus = Literal[RoundStatus.OPEN, RoundStatus.CLOSED, "none"]
"""A round as ``GET .../rounds/current`` shows it (none: no round has opened yet)."""


# --- the round watcher ------------------------------------------------------------------------


@dataclass(frozen=True)
class RoundSnapshot:
    """What this process last read of an auction's newest round."""

    head: crud.RoundHead
    body: crud.RoundBody | None
    """The round's rows, seeds and asked patrons (None when there is no round)."""

    @property
    def status(self) -> PublishedStatus:
        if self.head.status is None:
            return "none"
        return RoundStatus.OPEN if self.head.status == RoundStatus.OPEN else RoundStatus.CLOSED

    @property
    def auction_over(self) -> bool:
        return self.head.auction_status not in AUCTION_UNFINISHED

    def ready(self, after: int) -> bool:
        """Worth answering a long poll: a round above ``after`` is open, or the auction ended."""
        return self.auction_over or (
            self.status == RoundStatus.OPEN and (self.head.round or 0) > after
        )


@dataclass
class _Watch:
    """One watched auction: its latest snapshot, the read in flight, its waiters."""

    snapshot: RoundSnapshot | None = None
    read_at: float = -1.0
    reading: asyncio.Future[RoundSnapshot | None] | None = None
    changed: asyncio.Event = field(default_factory=asyncio.Event)
    waiters: int = 0
    poller: asyncio.Task[None] | None = None
    template: tuple[int | None, str, bytes, bytes] | None = None
    """(round id, status, body before and after ``seconds_left``) of the last answer built."""


class TooManyWaitersError(RuntimeError):
    """This process already holds ``MAX_WAITERS`` round requests."""


class RoundWatcher:
    """Long polls of ``GET /auctions/{id}/rounds/current`` (see the module docstring)."""

    def __init__(self, database: Database, writer: UploadWriter) -> None:
        self._database = database
        self._writer = writer
        self._watches: dict[int, _Watch] = {}
        self._waiters = 0

    async def current(self, auction_id: int, *, wait_s: float, after: int) -> bytes | None:
        """The answer body for the auction's newest round (None: no such auction), after up to
        ``wait_s`` seconds of waiting for a round above ``after`` to open."""
        loop = asyncio.get_running_loop()
        watch = self._watches.setdefault(auction_id, _Watch())
        snapshot = await self._fresh(auction_id, watch)
        if snapshot is None:
            self._watches.pop(auction_id, None)
            return None
        give_up = loop.time() + min(wait_s, MAX_WAIT_S)
        while not snapshot.ready(after) and loop.time() < give_up:
            if self._waiters >= MAX_WAITERS:
                raise TooManyWaitersError(f"{MAX_WAITERS} round requests are waiting already")
            self._waiters += 1
            watch.waiters += 1
            if watch.poller is None or watch.poller.done():
                watch.poller = asyncio.create_task(self._poll(auction_id, watch))
            try:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(watch.changed.wait(), give_up - loop.time())
            finally:
                self._waiters -= 1
                watch.waiters -= 1
            if watch.snapshot is None:
                self._watches.pop(auction_id, None)
                return None
            snapshot = watch.snapshot
        body = self._answer(auction_id, watch, snapshot)
        if snapshot.head.round_id is not None:
            self._writer.count_published(snapshot.head.round_id, len(body))
        self._forget_idle()
        return body

    def _forget_idle(self) -> None:
        """Beyond ``MAX_WATCHED`` auctions, forget those nobody waits on, least recently read
        first (a forgotten auction's next request reads it afresh)."""
        if len(self._watches) <= MAX_WATCHED:
            return
        idle = sorted(
            (w.read_at, a) for a, w in self._watches.items() if w.waiters == 0 and w.reading is None
        )
        for _, auction_id in idle[: len(self._watches) - MAX_WATCHED]:
            del self._watches[auction_id]

    async def _fresh(self, auction_id: int, watch: _Watch) -> RoundSnapshot | None:
        """The snapshot, read again if older than ``WATCH_POLL_S`` (one read shared by all)."""
        loop = asyncio.get_running_loop()
        if watch.snapshot is not None and loop.time() - watch.read_at < WATCH_POLL_S:
            return watch.snapshot
        if watch.reading is None:
            watch.reading = asyncio.ensure_future(self._read(auction_id, watch))
        return await asyncio.shield(watch.reading)

    async def _read(self, auction_id: int, watch: _Watch) -> RoundSnapshot | None:
        try:
            known = watch.snapshot
            snapshot = await run_in_threadpool(self._query, auction_id, known)
            watch.snapshot, watch.read_at = snapshot, asyncio.get_running_loop().time()
            if snapshot is None or known is None or _key(snapshot) != _key(known):
                watch.changed.set()
                watch.changed = asyncio.Event()
            return snapshot
        finally:
            watch.reading = None

    def _query(self, auction_id: int, known: RoundSnapshot | None) -> RoundSnapshot | None:
        with self._database.session(write=False) as session:
            head = crud.round_head(session, auction_id=auction_id)
            if head is None:
                return None
            if head.round_id is None:
                return RoundSnapshot(head, None)
            if known is not None and known.head.round_id == head.round_id:
                return RoundSnapshot(head, known.body)  # the rows of a round never change
            return RoundSnapshot(head, crud.round_body(session, round_id=head.round_id))

    async def _poll(self, auction_id: int, watch: _Watch) -> None:
        """Read the auction again every ``WATCH_POLL_S`` while anyone waits on it."""
        try:
            while watch.waiters > 0:
                await self._fresh(auction_id, watch)
                await asyncio.sleep(WATCH_POLL_S)
        except Exception:  # a failed read wakes the waiters, who answer what they have
            log.exception("watching the rounds of auction %d failed", auction_id)
            watch.changed.set()
            watch.changed = asyncio.Event()

    def _answer(self, auction_id: int, watch: _Watch, snapshot: RoundSnapshot) -> bytes:
        """The JSON answer (see ``RoundPublic``): built once per round and status."""
        head = snapshot.head
        status = snapshot.status
        if watch.template is None or watch.template[:2] != (head.round_id, status):
            before, after = _template(auction_id, snapshot)
            watch.template = (head.round_id, status, before, after)
        _, _, before, after = watch.template
        left = 0.0
        if status == RoundStatus.OPEN and head.deadline is not None:
            left = max(0.0, (head.deadline - utcnow()).total_seconds())
        return before + json.dumps(round(left, 3)).encode() + after

    async def close(self) -> None:
        """Stop the pollers (the waiters get their answers from the last snapshot)."""
        for watch in self._watches.values():
            if watch.poller is not None:
                watch.poller.cancel()
        self._watches.clear()


def _key(snapshot: RoundSnapshot) -> tuple[Any, ...]:
    head = snapshot.head
    return (head.auction_status, head.round_id, head.status)


_SECONDS_LEFT = "\x00seconds_left\x00"


def _template(auction_id: int, snapshot: RoundSnapshot) -> tuple[bytes, bytes]:
    """The answer's bytes before and after its ``seconds_left`` value."""
    head, body = snapshot.head, snapshot.body
    is_open = snapshot.status == RoundStatus.OPEN and body is not None
    answer: dict[str, Any] = {
        "auction_id": auction_id,
        "auction_status": head.auction_status,
        "fine_tune_mode": head.fine_tune_mode,
        "fine_tune_rounds": head.fine_tune_rounds,
        "round": head.round,
        "iteration": head.iteration,
        "status": snapshot.status,
        "deadline": None if head.deadline is None else _utc(head.deadline),
        "seconds_left": _SECONDS_LEFT,
        "rows": body.rows if is_open and body is not None else None,
        "fine_tune_seed": None if body is None else body.fine_tune_seed,
        "augmentation_seed": None if body is None else body.augmentation_seed,
        "asked": body.asked if is_open and body is not None else [],
    }
    text = json.dumps(answer, separators=(",", ":"), allow_nan=False)
    before, after = text.split(json.dumps(_SECONDS_LEFT))
    return before.encode(), after.encode()


def _utc(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")


# --- the upload writer ------------------------------------------------------------------------

UploadKind = Literal["version", "unchanged", "late"]


@dataclass(frozen=True)
class UploadRequest:
    """An upload that passed the route's checks, to be stored (or found late)."""

    kind: UploadKind
    """version: store the manifest as a new version (accepted or refused by ``verdict``);
    unchanged: the patron's current weights, acknowledged without a new version; late: past
    the deadline or closed, only marked."""
    round_number: int
    round_id: int
    position: int
    participant_id: int
    current_id: int
    current_version: int
    auction_id: int
    body_sha256: str
    bytes_in: int
    manifest: dict[str, Any] | None = None
    verdict: Verdict | None = None


@dataclass(frozen=True)
class Answered:
    """The upload's answer, exactly the bytes sent (repeats get the same bytes)."""

    body: bytes


@dataclass(frozen=True)
class UploadRefused:
    """An error answer: status, message, the location it names, the error type."""

    status: int
    msg: str
    loc: tuple[str | int, ...]
    kind: str


UploadOutcome = Answered | UploadRefused


@dataclass
class _Queued:
    request: UploadRequest
    loop: asyncio.AbstractEventLoop
    future: asyncio.Future[UploadOutcome]


class _ConflictError(Exception):
    """A statement of the group hit a unique constraint."""


def _late(request: UploadRequest) -> UploadRefused:
    return UploadRefused(
        410,
        f"round {request.round_number} is closed or past its deadline: the upload is late "
        "and was not applied",
        ("path", "round"),
        "round_closed",
    )


def _different(request: UploadRequest) -> UploadRefused:
    return UploadRefused(
        409,
        f"this patron already answered round {request.round_number} with another body: one "
        "upload per round",
        ("path", "round"),
        "already_answered",
    )


def answer_bytes(answer: dict[str, Any]) -> bytes:
    """The JSON bytes of an upload's answer (compact; a stored answer gives the same bytes)."""
    return json.dumps(answer, separators=(",", ":"), allow_nan=False).encode()


_INSERT_ANSWERS = insert(FineTuneAnswer.__table__)  # type: ignore[arg-type]
"""Core (not the ORM's bulk path): a group's answers in one multi-row statement."""


def _store_group(session: Session, group: list[UploadRequest]) -> list[UploadOutcome]:
    """Decide the group's uploads in arrival order against the database and write them."""
    round_ids = sorted({item.round_id for item in group})
    rounds = {
        row.id: row
        for row in session.connection().execute(
            select(FineTuneRound.id, FineTuneRound.status, FineTuneRound.deadline)
            .where(FineTuneRound.id.in_(round_ids))
            .with_for_update(read=True)
        )
    }
    positions = sorted({item.position for item in group})
    existing = {
        (row.round_id, row.position): row
        for row in session.connection().execute(
            select(
                FineTuneAnswer.id,
                FineTuneAnswer.round_id,
                FineTuneAnswer.position,
                FineTuneAnswer.outcome,
                FineTuneAnswer.body_sha256,
                FineTuneAnswer.answer,
            ).where(FineTuneAnswer.round_id.in_(round_ids), FineTuneAnswer.position.in_(positions))
        )
    }
    now = utcnow()
    new_versions = [item for item in group if item.kind == "version"]
    participants = sorted({item.participant_id for item in new_versions})
    if participants:  # version numbers are taken under the participants' row locks
        session.connection().execute(
            select(Participant.id).where(Participant.id.in_(participants)).with_for_update()
        )
    next_version = {
        pid: version + 1
        for pid, version in crud.latest_versions(session, participant_ids=participants).items()
    }
    outcomes: list[UploadOutcome | None] = []
    decided: dict[tuple[int, int], tuple[str, int]] = {}  # (round, position) → sha, its index
    repeats: list[tuple[int, int]] = []  # (index, index of the same upload earlier in the group)
    versions: list[dict[str, Any]] = []
    answers: list[tuple[int, dict[str, Any]]] = []  # outcome index, answer row
    lates: list[tuple[UploadRequest, int | None]] = []
    for index, item in enumerate(group):
        key = (item.round_id, item.position)
        stored = existing.get(key)
        if key in decided:
            sha, first = decided[key]
            if sha == item.body_sha256:
                repeats.append((index, first))
                outcomes.append(None)
            else:
                outcomes.append(_different(item))
            continue
        if stored is not None and stored.outcome in ANSWERED:
            same = stored.body_sha256 == item.body_sha256
            body = answer_bytes(stored.answer or {})
            outcomes.append(Answered(body) if same else _different(item))
            continue
        current = rounds.get(item.round_id)
        if (
            item.kind == "late"
            or current is None
            or current.status != RoundStatus.OPEN
            or (now >= current.deadline)
        ):
            if stored is None or stored.outcome == AnswerOutcome.MISSING:
                lates.append((item, None if stored is None else stored.id))
            outcomes.append(_late(item))
            continue
        answer: dict[str, Any] = {
            "round": item.round_number,
            "accepted": True,
            "reasons": [],
            "version": item.current_version,
            "model_id": item.current_id,
            "parent_id": item.current_id,
            "uploaded_id": None,
        }
        row: dict[str, Any] = {
            "round_id": item.round_id,
            "position": item.position,
            "outcome": AnswerOutcome.ACCEPTED,
            "model_id": item.current_id,
            "uploaded_id": None,
            "body_sha256": item.body_sha256,
            "bytes_in": item.bytes_in,
            "created_at": now,
        }
        if item.kind == "version":
            assert item.manifest is not None and item.verdict is not None
            number = next_version[item.participant_id]
            next_version[item.participant_id] = number + 1
            accepted = item.verdict.accepted
            answer.update(
                accepted=accepted,
                reasons=[reason.to_dict() for reason in item.verdict.reasons],
            )
            row["outcome"] = AnswerOutcome.ACCEPTED if accepted else AnswerOutcome.REFUSED
            versions.append(
                {
                    "participant_id": item.participant_id,
                    "version": number,
                    "manifest": item.manifest,
                    "accepted": accepted,
                    "reasons": answer["reasons"],
                    "created_at": now,
                    "parent_id": item.current_id,
                    "auction_id": item.auction_id,
                    "round": item.round_number,
                }
            )
            row["_version_number"] = number
        answers.append((index, row))
        answer["outcome"] = row["outcome"]
        row["answer"] = answer
        outcomes.append(None)
        decided[key] = (item.body_sha256, index)
    version_ids = iter(crud.insert_model_versions(session, rows=versions))
    inserted = []
    for index, row in answers:
        answer = row["answer"]
        number = row.pop("_version_number", None)
        if number is not None:
            uploaded = next(version_ids)
            row["uploaded_id"] = answer["uploaded_id"] = uploaded
            if answer["accepted"]:
                row["model_id"] = answer["model_id"] = uploaded
                answer["version"] = number
        body = answer_bytes(answer)
        row["bytes_out"] = len(body)
        outcomes[index] = Answered(body)
        inserted.append(row)
    for index, first in repeats:
        outcomes[index] = outcomes[first]
    if inserted:
        session.connection().execute(_INSERT_ANSWERS, inserted)
    for item, answer_id in lates:
        if answer_id is None:
            session.connection().execute(
                _INSERT_ANSWERS,
                [
                    {
                        "round_id": item.round_id,
                        "position": item.position,
                        "outcome": AnswerOutcome.LATE,
                        "model_id": item.current_id,
                        "body_sha256": item.body_sha256,
                        "bytes_in": item.bytes_in,
                        "bytes_out": 0,
                        "created_at": now,
                    }
                ],
            )
        else:
            session.execute(
                update(FineTuneAnswer)
                .where(
                    FineTuneAnswer.id == answer_id,
                    FineTuneAnswer.outcome == AnswerOutcome.MISSING,
                )
                .values(
                    outcome=AnswerOutcome.LATE, body_sha256=item.body_sha256, bytes_in=item.bytes_in
                )
            )
    return [outcome for outcome in outcomes if outcome is not None]


class UploadWriter:
    """``await store(request)`` from any event loop; the writes happen on one thread, grouped."""

    def __init__(self, database: Database) -> None:
        self._database = database
        self._queue: queue.SimpleQueue[_Queued | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="upload-writer", daemon=True)
        self._published: dict[int, int] = defaultdict(int)
        self._published_lock = threading.Lock()
        self._closed = False
        self.groups = 0
        """Transactions committed so far (diagnostics and tests)."""

    def start(self) -> None:
        self._thread.start()

    def count_published(self, round_id: int, n_bytes: int) -> None:
        """Add to a round's published-bytes counter (written within ``FLUSH_S``)."""
        with self._published_lock:
            self._published[round_id] += n_bytes

    async def store(self, request: UploadRequest) -> UploadOutcome:
        """Store one upload (or find it late, repeated, conflicting) and give its answer."""
        if self._closed:
            return UploadRefused(503, "the server is stopping", ("body",), "stopping")
        loop = asyncio.get_running_loop()
        future: asyncio.Future[UploadOutcome] = loop.create_future()
        self._queue.put(_Queued(request, loop, future))
        # Shielded: an agent that goes away does not un-write an upload already queued.
        return await asyncio.shield(future)

    def shutdown(self) -> None:
        """Write what is queued, then stop the thread."""
        self._closed = True
        self._queue.put(None)
        if self._thread.is_alive():
            self._thread.join(STOP_GRACE_S)

    def _run(self) -> None:
        stopping = False
        while not stopping:
            try:
                first = self._queue.get(timeout=FLUSH_S)
            except queue.Empty:
                self._flush_published()
                continue
            group: list[_Queued] = []
            if first is None:
                stopping = True
            else:
                group.append(first)
            while len(group) < MAX_GROUP and not stopping:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is None:
                    stopping = True
                else:
                    group.append(item)
            if group:
                try:
                    outcomes = self._write([q.request for q in group])
                except Exception as exc:  # never let the writer thread die
                    log.exception("an upload group failed")
                    outcomes = [_unavailable(exc)] * len(group)
                _deliver([(q.loop, q.future, o) for q, o in zip(group, outcomes, strict=True)])
            self._flush_published()

    def _write(self, group: list[UploadRequest]) -> list[UploadOutcome]:
        try:
            return self._transaction(group)
        except _ConflictError:
            if len(group) == 1:
                return [
                    UploadRefused(
                        409,
                        "the upload was written concurrently with another; retry",
                        ("path", "round"),
                        "conflict",
                    )
                ]
        return [outcome for item in group for outcome in self._write([item])]

    def _transaction(self, group: list[UploadRequest]) -> list[UploadOutcome]:
        try:
            with self._database.session(write=True) as session:
                outcomes = _store_group(session, group)
                session.commit()
        except IntegrityError as exc:
            raise _ConflictError from exc
        except OperationalError as exc:
            log.error("upload group of %d not stored: %s", len(group), exc)
            return [_unavailable(exc)] * len(group)
        self.groups += 1
        return outcomes

    def _flush_published(self) -> None:
        with self._published_lock:
            counts, self._published = dict(self._published), defaultdict(int)
        if not counts:
            return
        try:
            with self._database.session(write=True) as session:
                crud.add_published_bytes(session, counts=counts)
                session.commit()
        except OperationalError as exc:  # counted again at the next flush
            log.warning("published-bytes counters not written: %s", exc)
            with self._published_lock:
                for round_id, n_bytes in counts.items():
                    self._published[round_id] += n_bytes


def _unavailable(exc: Exception) -> UploadRefused:
    first_line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return UploadRefused(
        503, f"the database is unavailable: {first_line}", ("body",), "db_unavailable"
    )


Delivery = tuple[asyncio.AbstractEventLoop, "asyncio.Future[Any]", Any]
"""(the waiter's loop, its future, the result or the exception to give it)."""


def _deliver(deliveries: list[Delivery]) -> None:
    """Hand results computed on a thread to futures awaited on event loops."""
    by_loop: dict[asyncio.AbstractEventLoop, list[Delivery]] = defaultdict(list)
    for delivery in deliveries:
        by_loop[delivery[0]].append(delivery)
    for loop, mine in by_loop.items():
        with contextlib.suppress(RuntimeError):  # that loop has closed: nobody waits
            loop.call_soon_threadsafe(_settle, mine)


def _settle(deliveries: list[Delivery]) -> None:
    for _, future, value in deliveries:
        if future.done():
            continue
        if isinstance(value, BaseException):
            future.set_exception(value)
        else:
            future.set_result(value)


# --- the upload lookups -----------------------------------------------------------------------


@dataclass
class _Lookup:
    key: crud.UploadKey
    loop: asyncio.AbstractEventLoop
    future: asyncio.Future[crud.UploadTarget]


class UploadLookup:
    """``await get(key)``: what an upload is checked against (``crud.upload_targets``). One
    thread reads every lookup queued since its last pass in one transaction of six queries, so
    64 agents uploading at once cost a few reads, not 64 thread hops of four queries each."""

    def __init__(self, database: Database) -> None:
        self._database = database
        self._queue: queue.SimpleQueue[_Lookup | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="upload-lookup", daemon=True)

    def start(self) -> None:
        self._thread.start()

    async def get(self, key: crud.UploadKey) -> crud.UploadTarget:
        """The upload's target; raises ``crud.UploadLookupError`` (no such auction or model)
        or SQLAlchemy's OperationalError (the database is unavailable)."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[crud.UploadTarget] = loop.create_future()
        self._queue.put(_Lookup(key, loop, future))
        return await future

    def shutdown(self) -> None:
        self._queue.put(None)
        if self._thread.is_alive():
            self._thread.join(STOP_GRACE_S)

    def _run(self) -> None:
        while True:
            first = self._queue.get()
            if first is None:
                return
            batch = [first]
            while len(batch) < MAX_GROUP:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is None:
                    self._queue.put(None)  # stop after this batch
                    break
                batch.append(item)
            results: list[Any]
            try:
                with self._database.session(write=False) as session:
                    results = crud.upload_targets(session, keys=[item.key for item in batch])
            except Exception as exc:  # never let the thread die; each lookup gets the error
                log.exception("an upload lookup batch failed")
                results = [exc] * len(batch)
            _deliver([(item.loop, item.future, r) for item, r in zip(batch, results, strict=True)])
