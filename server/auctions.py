"""Auctions in the background, in spawned worker processes (reused from auction to auction).

The worker drives ``sim.market.Market`` one round at a time. After every round it commits, in
ONE transaction, the round's row, its purchases and quits, the auction's new price and supply,
and the market checkpoint (RNG state included). The commit is conditional on the auction still
standing at that round, so a second runner (or a stale one) can never add or duplicate a row.

A pending or running auction nobody holds the lease of (its server restarted or died) is
claimed again (``server.runner``); its worker restores the market from the last committed
checkpoint and continues bit-identically. An auction that cannot be resumed (checkpoint
unreadable, round count disagreeing) is marked failed with the reason.

Remote fine-tuning (``fine_tune_mode`` "remote"): an iteration after which the patrons
fine-tune is committed together with an open ``FineTuneRound`` row (rows, seeds, the asked
patrons, an absolute deadline). The worker then counts the answers the screening process
stores, until every asked patron has answered or the deadline has passed, whichever comes
first. It counts them (and reads and parses the versions accepted so far, ``_Versions``)
whenever the upload writer rings the round's doorbell after storing answers
(``server.doorbell``), and at the bell's fallback period. It closes the round in ONE
transaction, which also plays the next iteration: the round's status, a ``missing`` answer for
each silent patron, the accepted versions applied to the market, the next iteration's row
(with the round it opens, if any) and the new checkpoint, all at one timestamp (the round's
``closed_at`` is the next round's ``opened_at``). After each of its commits it rings
the round watcher of the API process that started it. A restart in the middle of a round
finds the round still open (its checkpoint is the one from before the round) and waits for it
again until the same deadline; nothing is applied twice.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import TYPE_CHECKING, NamedTuple, TypeVar

from sqlalchemy import Connection, Text, bindparam, cast, insert, select, update
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, selectinload, undefer

from agents.manifest import Manifest, parse_manifest, parse_manifest_json
from server import crud, doorbell
from server.db import Database
from server.models import (
    Auction,
    AuctionIteration,
    AuctionPatron,
    FineTuneAnswer,
    FineTuneRound,
    ModelVersion,
    Purchase,
    Quit,
    utcnow,
)
from server.runner import WorkKind
from server.status import ANSWERED, AUCTION_UNFINISHED, AnswerOutcome, AuctionStatus, RoundStatus
from server.workers import WorkerContext, error_summary
from sim.market import MarketConfig

if TYPE_CHECKING:
    from sim.market import IterationRecord, Market, RescreenBatch

log = logging.getLogger("srd.auctions")
_T = TypeVar("_T")

ROUND_POLL_S = 0.002
"""How often a worker looks for the answers of its open fine-tuning round where it has no
doorbell (``server.doorbell``; elsewhere it counts them when rung, and at the bell's fallback
period): the round closes within this long of its last answer."""


class ResumeError(RuntimeError):
    """The auction's stored state cannot be continued."""


@dataclass(frozen=True)
class _OpenRound:
    """What the worker needs of an open fine-tuning round: its id, the asked patrons' positions
    and its deadline."""

    id: int
    asked: list[int]
    deadline: datetime


def base_price() -> float:
    """The opening price of every auction (the market's default)."""
    return MarketConfig(n_fish=1).base_price


def _market_config(auction: Auction) -> MarketConfig:
    return MarketConfig(
        n_fish=auction.n_initial,
        max_iterations=auction.max_iterations,
        fine_tune=auction.fine_tune,
        fine_tune_rounds=auction.fine_tune_rounds,
        fine_tune_mode="remote" if auction.fine_tune_mode == "remote" else "server",
        seed=auction.seed,
    )


def rescreening() -> RescreenBatch:
    """The re-screening of a server-mode auction's fine-tuned patrons: a patron stays in only
    while the screener still accepts it (the one re-screening the study uses too)."""
    from screener import rescreen

    return rescreen


def _load_market(auction: Auction, manifests: Sequence[Manifest]) -> Market:
    # The market (and torch) is imported here, in the worker: the API process imports this
    # module for its work kind and never plays an auction itself.
    from sim.market import Market

    config = _market_config(auction)
    # Remote rounds are re-screened by the API as each upload arrives.
    judge = rescreening() if auction.fine_tune and config.fine_tune_mode == "server" else None
    if auction.checkpoint is None:
        if auction.iteration != 0:
            raise ResumeError(f"{auction.iteration} rounds are committed but no checkpoint is")
        return Market(manifests, config, rescreen_batch=judge)
    try:
        restored = Market.restore(manifests, config, auction.checkpoint, rescreen_batch=judge)
    except Exception as exc:
        raise ResumeError(f"the checkpoint cannot be restored: {exc}") from exc
    if restored.iteration != auction.iteration:
        raise ResumeError(
            f"checkpoint is at round {restored.iteration}, database at {auction.iteration}"
        )
    return restored


def _commit_round(
    session: Session,
    auction_id: int,
    record: IterationRecord,
    blob: bytes,
    model_ids: list[int],
    deadline_s: float,
    market: Market,
    now: datetime,
) -> tuple[bool, _OpenRound | None]:
    """Write one iteration begun at ``now`` atomically, with the fine-tuning round it opens (the
    market's pending round, open from ``now``, due ``deadline_s`` after this commit) if any;
    whether it was written (False when the auction moved on without us) and the round it
    opened."""
    opened = market.pending_round
    moved = session.execute(
        update(Auction)
        .where(
            Auction.id == auction_id,
            Auction.iteration == record.iteration,
            Auction.status == AuctionStatus.RUNNING,
        )
        .values(
            iteration=record.iteration + 1,
            price=record.next_price,
            n_available=record.n_available_after,
            checkpoint=blob,
            status=AuctionStatus.FINISHED if record.finished else AuctionStatus.RUNNING,
            stop_reason=record.stop_reason,
            finished_at=now if record.finished else None,
            updated_at=now,
        )
    )
    if moved.rowcount != 1:  # type: ignore[attr-defined]
        session.rollback()
        return False, None
    connection = session.connection()
    connection.execute(
        insert(AuctionIteration),
        {
            "auction_id": auction_id,
            "iteration": record.iteration,
            "price": record.price,
            "n_available": record.n_available,
            "votes": dict(record.votes),
            "row_votes": dict(record.row_votes),
            "next_price": record.next_price,
            "n_available_after": record.n_available_after,
            "created_at": now,
            "explanations": {
                "row": record.row,
                "patrons": [
                    {**vote, "model_id": model_ids[vote["patron"]]}
                    for vote in record.explained()["patrons"]
                ],
            },
        },
    )
    if record.buyers:
        connection.execute(
            insert(Purchase),
            [
                {
                    "auction_id": auction_id,
                    "model_id": model_ids[i],
                    "price": price,
                    "iteration": record.iteration,
                }
                for i, price in record.buyers
            ],
        )
    if record.quitters:
        connection.execute(
            insert(Quit),
            [
                {"auction_id": auction_id, "model_id": model_ids[i], "iteration": record.iteration}
                for i in record.quitters
            ],
        )
    row = None
    if opened is not None:
        deadline = utcnow() + timedelta(seconds=deadline_s)
        round_id = connection.execute(
            insert(FineTuneRound).returning(FineTuneRound.id),
            {
                "auction_id": auction_id,
                "round": opened.iteration + 1,
                "iteration": opened.iteration,
                "status": RoundStatus.OPEN,
                "opened_at": now,
                "deadline": deadline,
                "rows": opened.rows.tolist(),
                "fine_tune_seed": opened.fine_tune_seed,
                "augmentation_seed": opened.augmentation_seed,
                "asked": opened.patrons,
                "bytes_published": 0,
            },
        ).scalar_one()
        row = _OpenRound(round_id, list(opened.patrons), deadline)
    session.commit()
    return True, row


class _Answer(NamedTuple):
    """An answer of a round as the worker counts and applies it."""

    position: int
    outcome: str
    uploaded_id: int | None
    """The version its upload stored (null if none was)."""


class _Versions:
    """The versions a round's accepted uploads store, parsed as the answers come in while the
    worker waits, so that closing the round reads and parses none of them (versions never
    change once stored)."""

    def __init__(self) -> None:
        self.manifests: dict[int, Manifest] = {}

    def answers(self, connection: Connection, round_id: int) -> list[_Answer]:
        """Every answer of the round so far (position, outcome, uploaded version); the versions
        of the accepted ones not read yet are read (a second query, only when there are any)
        and parsed from their JSON text."""
        answers = [
            _Answer(position, outcome, uploaded_id)
            for position, outcome, uploaded_id in connection.execute(
                _ANSWERS, {"round_id": round_id}
            )
        ]
        wanted = [
            a.uploaded_id for a in answers if _applies(a) and a.uploaded_id not in self.manifests
        ]
        if wanted:
            for version_id, text in connection.execute(_MANIFESTS, {"ids": wanted}):
                self.manifests[version_id] = parse_manifest_json(text)
        return answers


_ANSWERS = select(
    FineTuneAnswer.position, FineTuneAnswer.outcome, FineTuneAnswer.uploaded_id
).where(FineTuneAnswer.round_id == bindparam("round_id"))
"""A round's answers (one statement, the same text every time)."""
_MANIFESTS = select(ModelVersion.id, cast(ModelVersion.manifest, Text)).where(
    ModelVersion.id.in_(bindparam("ids", expanding=True))
)
"""Versions' manifests as their stored JSON text (parsed by pydantic in one pass)."""


def _applies(answer: _Answer) -> bool:
    """An accepted upload that stored a new version."""
    return answer.outcome == AnswerOutcome.ACCEPTED and answer.uploaded_id is not None


def _wait_for_answers(
    database: Database, round_id: int, asked: int, deadline: float, versions: _Versions
) -> None:
    """Until ``asked`` patrons have answered the round or the wall-clock ``deadline`` (epoch
    seconds) has passed, whichever comes first; the accepted versions are read as they come."""
    # Listening before the first count: a ring for an answer stored after it is never lost.
    bell = doorbell.listen(doorbell.scope(database.url), doorbell.round_bell(round_id))
    reader = _Reader(database)
    try:
        while True:
            found = reader.read(lambda connection: versions.answers(connection, round_id))
            answered = sum(1 for a in found if a.outcome in ANSWERED)
            left = deadline - time.time()
            if answered >= asked or left <= 0:
                return
            if bell is None:
                time.sleep(min(ROUND_POLL_S, left))
            else:
                bell.wait(min(doorbell.FALLBACK_S, left))
    finally:
        reader.close()
        if bell is not None:
            bell.close()


class _Reader:
    """One connection kept for a wait's many small reads (no session, no pool checkout per
    read); each read is its own transaction. A read that fails on a connection the database
    dropped (a restart) is tried once more on a fresh one."""

    def __init__(self, database: Database) -> None:
        self._engine = database.engine
        self._connection: Connection | None = None

    def read(self, query: Callable[[Connection], _T]) -> _T:
        try:
            return self._read(query)
        except DBAPIError:
            self.close()
            return self._read(query)

    def _read(self, query: Callable[[Connection], _T]) -> _T:
        if self._connection is None:
            self._connection = self._engine.connect()
        result = query(self._connection)
        self._connection.rollback()
        return result

    def close(self) -> None:
        if self._connection is not None:
            with contextlib.suppress(Exception):
                self._connection.close()
            self._connection = None


def _close_round(
    session: Session,
    auction_id: int,
    market: Market,
    row: _OpenRound,
    now: datetime,
    versions: _Versions,
) -> bool:
    """Close the open round ``row`` at ``now`` in the transaction of ``session``: its status,
    its answers applied to the market (see ``_apply_answers``); False when another runner
    closed it."""
    closed = session.execute(
        update(FineTuneRound)
        .where(FineTuneRound.id == row.id, FineTuneRound.status == RoundStatus.OPEN)
        .values(status=RoundStatus.CLOSED, closed_at=now)
    )
    if closed.rowcount != 1:  # type: ignore[attr-defined]
        return False
    _apply_answers(session, auction_id, row, market, now, versions)
    return True


def _open_round(database: Database, auction_id: int, number: int) -> _OpenRound:
    """The auction's fine-tuning round ``number``, which the checkpoint awaits: open (read on
    a resume; the worker knows the rounds it opens itself)."""
    with database.session(write=False) as session:
        row = session.scalars(
            select(FineTuneRound).where(
                FineTuneRound.auction_id == auction_id, FineTuneRound.round == number
            )
        ).one_or_none()
    if row is None or row.status != RoundStatus.OPEN:
        raise ResumeError(f"the checkpoint awaits fine-tuning round {number}, which is not open")
    return _OpenRound(row.id, list(row.asked), row.deadline)


def _apply_answers(
    session: Session,
    auction_id: int,
    row: _OpenRound,
    market: Market,
    now: datetime,
    versions: _Versions,
) -> None:
    """Apply the round's accepted uploads to the market and to the patrons' current versions,
    and record a ``missing`` answer for every asked patron that stayed silent."""
    connection = session.connection()
    answered = {a.position: a for a in versions.answers(connection, row.id)}
    applied = {p: a.uploaded_id for p, a in answered.items() if _applies(a)}
    market.apply_round({p: versions.manifests[i] for p, i in applied.items() if i is not None})
    silent = [p for p in row.asked if p not in answered]
    if silent:
        bidding = {
            patron.position: patron.current_model_id or patron.model_id
            for patron in connection.execute(
                select(
                    AuctionPatron.position, AuctionPatron.model_id, AuctionPatron.current_model_id
                ).where(AuctionPatron.auction_id == auction_id, AuctionPatron.position.in_(silent))
            )
        }
        connection.execute(
            insert(FineTuneAnswer),
            [
                {
                    "round_id": row.id,
                    "position": position,
                    "outcome": AnswerOutcome.MISSING,
                    "model_id": bidding[position],
                    "bytes_in": 0,
                    "bytes_out": 0,
                    "created_at": now,
                }
                for position in silent
            ],
        )
    if applied:
        connection.execute(
            update(AuctionPatron)
            .where(
                AuctionPatron.auction_id == auction_id,
                AuctionPatron.position == bindparam("at"),
            )
            .values(current_model_id=bindparam("version")),
            [{"at": position, "version": version} for position, version in applied.items()],
        )


def _mark_failed(database: Database, auction_id: int, reason: str) -> None:
    with database.session(write=True) as session:
        crud.fail_unfinished(session, table=Auction, row_id=auction_id, error=reason)
        session.commit()


def _drive(database: Database, auction_id: int) -> None:
    # Read and rebuild the market outside any write transaction (parsing the manifests and
    # building the market take a while; on SQLite a write transaction holds the one write lock).
    with database.session(write=False) as session:
        auction = session.scalars(
            select(Auction)
            .where(Auction.id == auction_id)
            .options(undefer(Auction.checkpoint), selectinload(Auction.patrons))
        ).one_or_none()
        if auction is None or auction.status not in AUCTION_UNFINISHED:
            return
        model_ids = [patron.model_id for patron in auction.patrons]
        manifests = _patron_manifests(session, auction.patrons)
    market = _load_market(auction, manifests)
    with database.session(write=True) as session:
        now = utcnow()
        values: dict[str, object] = {"status": AuctionStatus.RUNNING, "updated_at": now}
        if auction.status == AuctionStatus.PENDING:
            values["started_at"] = now
        if market.finished:  # nothing left to play (a market that ends before its first round)
            values.update(status=AuctionStatus.FINISHED, finished_at=now)
        claimed = session.execute(
            update(Auction)
            .where(
                Auction.id == auction_id,
                Auction.status == auction.status,
                Auction.iteration == auction.iteration,
            )
            .values(**values)
        )
        if claimed.rowcount != 1:  # type: ignore[attr-defined]
            log.warning("auction %d changed while it was being loaded; not driven", auction_id)
            return
        session.commit()
    bells, watchers = doorbell.scope(database.url), doorbell.watch_bell(os.getppid())
    deadline_s = auction.round_deadline_s
    opened: _OpenRound | None = None
    while not market.finished:
        pending = market.pending_round
        if pending is None:  # the iteration is computed before the write lock is taken
            began = utcnow()
            record, blob = market.step(), market.checkpoint()
            with database.session(write=True) as session:
                moved, opened = _commit_round(
                    session, auction_id, record, blob, model_ids, deadline_s, market, began
                )
        else:
            row = opened or _open_round(database, auction_id, pending.iteration + 1)
            versions = _Versions()
            _wait_for_answers(database, row.id, len(row.asked), row.deadline.timestamp(), versions)
            # One transaction: the round closed, its answers applied, the next iteration (a
            # remote auction's is its votes only: it fine-tunes nobody) and its checkpoint.
            with database.session(write=True) as session:
                now = utcnow()
                moved = _close_round(session, auction_id, market, row, now, versions)
                if not moved:
                    session.rollback()
                else:
                    record = market.step()
                    moved, opened = _commit_round(
                        session, auction_id, record, market.checkpoint(), model_ids, deadline_s,
                        market, now,
                    )  # fmt: skip
        if not moved:
            log.warning("auction %d moved on elsewhere; this runner stops", auction_id)
            return
        doorbell.ring(bells, watchers)


def _patron_manifests(session: Session, patrons: Sequence[AuctionPatron]) -> list[Manifest]:
    rows = session.scalars(
        select(ModelVersion).where(ModelVersion.id.in_([p.model_id for p in patrons]))
    ).all()
    by_id = {row.id: row for row in rows}
    return [parse_manifest(by_id[p.model_id].manifest) for p in patrons]


def run_auction(context: WorkerContext, auction_id: int) -> None:
    """Worker process entry point: play (or resume) one auction to its end."""
    database = Database(context.database_url)
    try:
        _drive(database, auction_id)
    except ResumeError as exc:
        _mark_failed(database, auction_id, f"cannot resume: {exc}")
    except Exception as exc:
        _mark_failed(database, auction_id, error_summary(exc))
    finally:
        database.close()


def _resume(session: Session, auction_ids: list[int]) -> None:
    """Claimed auctions need nothing: their worker resumes them from the last checkpoint."""


AUCTION_WORK = WorkKind(
    name="auction",
    table=Auction,
    task=run_auction,
    unfinished=AUCTION_UNFINISHED,
    timeout_setting="SRD_AUCTION_TIMEOUT_S",
    died="the auction worker exited (code {code}) before the auction finished",
    prepare=_resume,
)
"""Auctions as background work (``server.runner``)."""
