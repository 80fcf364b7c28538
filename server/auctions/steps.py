"""Auctions as a state machine in the database, moved by short steps in worker processes.

An auction's row says where it stands (status, iteration, price, supply, the market checkpoint
with its random state and fine-tuned weights) and when its next step is due
(``next_step_at``). The runner (``server.work.runner``) claims a due auction under a lease and hands
it to a worker process, which runs ONE step (``run_step``):

1. restore the market from the last committed checkpoint;
2. if a remote fine-tuning round is open: stop at once unless every asked patron has answered
   or the deadline has passed (the auction is then due again at the deadline); else judge the
   uploads still pending, close the round and apply its accepted versions;
3. play iterations until the auction ends or opens a fine-tuning round, committing each
   iteration in ONE transaction: its row, purchases and quits, the new price and supply, the
   checkpoint, the round it opens (rows, seeds, asked patrons, absolute deadline) and when the
   next step is due (now while it plays; the deadline while a round is open; never once ended).

An open round holds no process and no thread: the API stores the uploads and their verdicts
(``server.auctions.uploads``) and makes the auction due at once when every asked patron's upload
is judged. Every commit is conditional on the auction still standing where the step found it
(status running, the iteration expected, the round still open), so a stale or duplicated step
never writes twice, and a cancelled auction is never moved again. A step that dies (``kill
-9``) loses at most the iteration in flight: the auction is still due and the next step resumes
from the checkpoint, bit-identically. An auction whose stored state cannot be continued is
failed with the reason.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import TYPE_CHECKING

from sqlalchemy import func, insert, select, update
from sqlalchemy.orm import Session, selectinload, undefer

from agents.manifest import Manifest, parse_manifest
from server.store import crud
from server.store.db import Database, is_database_outage
from server.store.status import (
    ANSWERED,
    AUCTION_UNFINISHED,
    AnswerOutcome,
    AuctionStatus,
    RoundStatus,
)
from server.store.tables import (
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
from server.work.pool import WorkerContext, error_summary
from server.work.runner import WorkKind
from sim.market import MarketConfig

if TYPE_CHECKING:
    from sim.market import IterationRecord, Market, RescreenBatch

log = logging.getLogger("srd.auctions")


class ResumeError(RuntimeError):
    """The auction's stored state cannot be continued."""


@dataclass(frozen=True)
class _OpenRound:
    """What a step needs of an open fine-tuning round."""

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
        buy_fraction="staying" if auction.buy_fraction == "staying" else "all",
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


def _commit_iteration(
    session: Session,
    auction: Auction,
    record: IterationRecord,
    market: Market,
    model_ids: list[int],
    now: datetime,
) -> _OpenRound | None:
    """Write one iteration played at ``now`` (see the module docstring), with the round it
    opens (returned, if any); ``_MovedOnError`` when the auction moved on without this step."""
    opened = market.pending_round
    deadline = now + timedelta(seconds=auction.round_deadline_s)
    due = None if record.finished else (deadline if opened is not None else now)
    moved = session.execute(
        update(Auction)
        .where(
            Auction.id == auction.id,
            Auction.iteration == record.iteration,
            Auction.status == AuctionStatus.RUNNING,
        )
        .values(
            iteration=record.iteration + 1,
            price=record.next_price,
            n_available=record.n_available_after,
            checkpoint=market.checkpoint(),
            status=AuctionStatus.FINISHED if record.finished else AuctionStatus.RUNNING,
            stop_reason=record.stop_reason,
            finished_at=now if record.finished else None,
            updated_at=now,
            next_step_at=due,
        )
    )
    if moved.rowcount != 1:  # type: ignore[attr-defined]
        raise _MovedOnError(auction.id)
    crud.notify_change(session, kind="auction", row_id=auction.id)  # the round it opens or closes
    connection = session.connection()
    connection.execute(
        insert(AuctionIteration),
        {
            "auction_id": auction.id,
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
                    "auction_id": auction.id,
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
                {"auction_id": auction.id, "model_id": model_ids[i], "iteration": record.iteration}
                for i in record.quitters
            ],
        )
    if opened is None:
        return None
    rows = opened.rows.tolist()
    round_id = connection.execute(
        insert(FineTuneRound).returning(FineTuneRound.id),
        {
            "auction_id": auction.id,
            "round": opened.iteration + 1,
            "iteration": opened.iteration,
            "status": RoundStatus.OPEN,
            "opened_at": now,
            "deadline": deadline,
            "rows": rows,
            "fine_tune_seed": opened.fine_tune_seed,
            "augmentation_seed": opened.augmentation_seed,
            "asked": opened.patrons,
            # What publishing the round costs: its rows, once to every patron asked.
            "bytes_published": len(str(rows)) * len(opened.patrons),
        },
    ).scalar_one()
    return _OpenRound(round_id, list(opened.patrons), deadline)


class _MovedOnError(RuntimeError):
    """The auction is no longer where this step found it (cancelled, or moved by another)."""


class _PendingError(RuntimeError):
    """An upload of the round being closed still awaits its verdict."""


CLOSE_TRIES = 3
"""Times a step judges a round's pending uploads and tries to close it (an upload in time may
be stored while the step judges the others)."""


def _open_round(session: Session, auction_id: int) -> _OpenRound | None:
    row = session.scalars(
        select(FineTuneRound).where(
            FineTuneRound.auction_id == auction_id, FineTuneRound.status == RoundStatus.OPEN
        )
    ).one_or_none()
    return None if row is None else _OpenRound(row.id, list(row.asked), row.deadline)


def _answered(session: Session, round_id: int) -> int:
    return session.execute(
        select(func.count())
        .select_from(FineTuneAnswer)
        .where(FineTuneAnswer.round_id == round_id, FineTuneAnswer.outcome.in_(ANSWERED))
    ).scalar_one()


def _judge_pending(database: Database, round_id: int, margin: float) -> None:
    """Judge the round's uploads whose verdict the API never recorded (its screener was down,
    or it died): they came in time, so they count (held within ``margin`` of a bar)."""
    with database.session(write=False) as session:
        pending = crud.pending_uploads(session, round_id=round_id)
    if not pending:
        return
    from screener import rescreen_many

    verdicts = rescreen_many([parse_manifest(upload.manifest) for upload in pending])
    with database.session(write=True) as session:
        now = utcnow()
        for upload, verdict in zip(pending, verdicts, strict=True):
            crud.record_verdict(
                session, answer_id=upload.answer_id, verdict=verdict, margin=margin, now=now
            )
        session.commit()


def _close_round(
    session: Session, auction_id: int, market: Market, row: _OpenRound, now: datetime
) -> None:
    """Close the open round at ``now``: its accepted versions applied to the market and to the
    patrons' current versions, a ``missing`` answer for every asked patron that stayed silent."""
    closed = session.execute(
        update(FineTuneRound)
        .where(FineTuneRound.id == row.id, FineTuneRound.status == RoundStatus.OPEN)
        .values(status=RoundStatus.CLOSED, closed_at=now)
    )
    if closed.rowcount != 1:  # type: ignore[attr-defined]
        raise _MovedOnError(auction_id)
    connection = session.connection()
    answers = connection.execute(
        select(FineTuneAnswer.position, FineTuneAnswer.outcome, FineTuneAnswer.uploaded_id).where(
            FineTuneAnswer.round_id == row.id
        )
    ).all()
    if any(a.outcome == AnswerOutcome.PENDING for a in answers):
        raise _PendingError(row.id)  # stored after the step judged the rest: judge it too
    applied = {
        a.position: a.uploaded_id
        for a in answers
        if a.outcome == AnswerOutcome.ACCEPTED and a.uploaded_id is not None
    }
    manifests = {
        version_id: parse_manifest(manifest)
        for version_id, manifest in connection.execute(
            select(ModelVersion.id, ModelVersion.manifest).where(
                ModelVersion.id.in_(list(applied.values()))
            )
        )
    }
    market.apply_round({p: manifests[i] for p, i in applied.items()})
    # A late upload already has its row (and keeps its outcome); the rest were silent.
    heard = {a.position for a in answers}
    silent = [p for p in row.asked if p not in heard]
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
        for position, version in applied.items():
            connection.execute(
                update(AuctionPatron)
                .where(AuctionPatron.auction_id == auction_id, AuctionPatron.position == position)
                .values(current_model_id=version)
            )


def _fail(database: Database, auction_id: int, reason: str) -> None:
    with database.session(write=True) as session:
        crud.fail_unfinished(session, table=Auction, row_id=auction_id, error=reason)
        session.commit()


def _not_yet(database: Database, auction_id: int, row: _OpenRound) -> bool:
    """An open round that may still hear answers: the auction is due again at its deadline
    (True); False when the round can close now."""
    with database.session(write=False) as session:
        answered = _answered(session, row.id)
    if answered >= len(row.asked) or utcnow() >= row.deadline:
        return False
    with database.session(write=True) as session:
        session.execute(
            update(Auction)
            .where(Auction.id == auction_id, Auction.status == AuctionStatus.RUNNING)
            .values(next_step_at=row.deadline)
        )
        session.commit()
    return True


def _step(database: Database, auction_id: int, margin: float) -> None:
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
        row = _open_round(session, auction_id)
        model_ids = [patron.model_id for patron in auction.patrons]
        manifests = _patron_manifests(session, auction.patrons)
    if row is not None and _not_yet(database, auction_id, row):
        return
    market = _load_market(auction, manifests)
    if auction.status == AuctionStatus.PENDING:
        _start(database, auction, market)
        if market.finished:
            return
    if market.pending_round is not None:
        if row is None:
            number = market.pending_round.iteration + 1
            raise ResumeError(
                f"the checkpoint awaits fine-tuning round {number}, which is not open"
            )
        for attempt in range(CLOSE_TRIES):
            _judge_pending(database, row.id, margin)
            # One transaction: the round closed, its answers applied, the next iteration.
            with database.session(write=True) as session:
                now = utcnow()
                try:
                    _close_round(session, auction_id, market, row, now)
                except _PendingError:
                    if attempt + 1 == CLOSE_TRIES:
                        raise
                    session.rollback()
                    continue
                record = market.step()
                opened = _commit_iteration(session, auction, record, market, model_ids, now)
                session.commit()
                break
        if opened is not None:
            return
    while not market.finished:
        began = utcnow()  # the iteration is computed before the write lock is taken
        record = market.step()
        with database.session(write=True) as session:
            opened = _commit_iteration(session, auction, record, market, model_ids, began)
            session.commit()
        if opened is not None:
            return


def _start(database: Database, auction: Auction, market: Market) -> None:
    """The first step of a pending auction: running from now (finished at once when its market
    ends before its first iteration)."""
    with database.session(write=True) as session:
        now = utcnow()
        values: dict[str, object] = {
            "status": AuctionStatus.RUNNING,
            "started_at": now,
            "updated_at": now,
        }
        if market.finished:
            values.update(status=AuctionStatus.FINISHED, finished_at=now, next_step_at=None)
        started = session.execute(
            update(Auction)
            .where(Auction.id == auction.id, Auction.status == AuctionStatus.PENDING)
            .values(**values)
        )
        if started.rowcount != 1:  # type: ignore[attr-defined]
            raise _MovedOnError(auction.id)
        crud.notify_change(session, kind="auction", row_id=auction.id)
        session.commit()


def _patron_manifests(session: Session, patrons: Sequence[AuctionPatron]) -> list[Manifest]:
    rows = session.scalars(
        select(ModelVersion).where(ModelVersion.id.in_([p.model_id for p in patrons]))
    ).all()
    by_id = {row.id: row for row in rows}
    return [parse_manifest(by_id[p.model_id].manifest) for p in patrons]


def run_step(context: WorkerContext, auction_id: int) -> None:
    """Worker process entry point: one step of the auction (see the module docstring)."""
    database = Database(context.database_url)
    try:
        _step(database, auction_id, context.review_margin)
    except _MovedOnError:
        log.info(
            "auction %d moved on without this step (cancelled, or stepped elsewhere)", auction_id
        )
    except ResumeError as exc:
        _fail(database, auction_id, f"cannot resume: {exc}")
    except Exception as exc:
        if is_database_outage(exc):  # nothing committed: the auction stays due, and is retried
            log.warning("auction %d: step not committed, database unavailable: %s", auction_id, exc)
            return
        _fail(database, auction_id, error_summary(exc))
    finally:
        database.close()


def _nothing_to_prepare(session: Session, auction_ids: list[int]) -> None:
    """Claimed auctions need nothing: their step resumes from the last checkpoint."""


AUCTION_WORK = WorkKind(
    name="auction",
    table=Auction,
    task=run_step,
    unfinished=AUCTION_UNFINISHED,
    timeout_setting="SRD_AUCTION_TIMEOUT_S",
    died="the worker of its steps died {times} times (last exit code {code})",
    prepare=_nothing_to_prepare,
    due=Auction.next_step_at,
    resumable=True,
)
"""Auctions as background work (``server.work.runner``): a claim runs one step."""
