"""Auctions in the background, in spawned worker processes (reused from auction to auction).

The worker drives ``sim.market.Market`` one round at a time. After every round it commits, in
ONE transaction, the round's row, its purchases and quits, the auction's new price and supply,
and the market checkpoint (RNG state included). The commit is conditional on the auction still
standing at that round, so a second runner (or a stale one) can never add or duplicate a row.

On restart, every pending or running auction is queued again; its worker restores the market
from the last committed checkpoint and continues bit-identically. An auction that cannot be
resumed (checkpoint unreadable, round count disagreeing) is marked failed with the reason.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from sqlalchemy import select, update
from sqlalchemy.orm import Session, selectinload, undefer

from agents.manifest import Manifest, parse_manifest
from screener import screen
from server import crud
from server.db import Database
from server.models import (
    Auction,
    AuctionIteration,
    AuctionPatron,
    ModelVersion,
    Purchase,
    Quit,
    utcnow,
)
from server.workers import WorkerContext, WorkerPool, error_summary
from sim.market import IterationRecord, Market, MarketConfig

log = logging.getLogger("srd.auctions")

UNFINISHED = ("pending", "running")


class ResumeError(RuntimeError):
    """The auction's stored state cannot be continued."""


def base_price() -> float:
    """The opening price of every auction (the market's default)."""
    return MarketConfig(n_fish=1).base_price


def _rescreen(_patron: int, manifest: Manifest) -> bool:
    """A fine-tuned patron stays in only while the screener still accepts it."""
    return screen(manifest).accepted


def _market_config(auction: Auction) -> MarketConfig:
    return MarketConfig(
        n_fish=auction.n_initial,
        max_iterations=auction.max_iterations,
        fine_tune=auction.fine_tune,
        seed=auction.seed,
    )


def _load_market(auction: Auction, manifests: Sequence[Manifest]) -> Market:
    config = _market_config(auction)
    rescreen = _rescreen if auction.fine_tune else None
    if auction.checkpoint is None:
        if auction.iteration != 0:
            raise ResumeError(f"{auction.iteration} rounds are committed but no checkpoint is")
        return Market(manifests, config, rescreen=rescreen)
    try:
        restored = Market.restore(manifests, config, auction.checkpoint, rescreen=rescreen)
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
) -> bool:
    """Write one round atomically; False when the auction moved on without us."""
    now = utcnow()
    moved = session.execute(
        update(Auction)
        .where(
            Auction.id == auction_id,
            Auction.iteration == record.iteration,
            Auction.status == "running",
        )
        .values(
            iteration=record.iteration + 1,
            price=record.next_price,
            n_available=record.n_available_after,
            checkpoint=blob,
            status="finished" if record.finished else "running",
            stop_reason=record.stop_reason,
            finished_at=now if record.finished else None,
            updated_at=now,
        )
    )
    if moved.rowcount != 1:  # type: ignore[attr-defined]
        session.rollback()
        return False
    session.add(
        AuctionIteration(
            auction_id=auction_id,
            iteration=record.iteration,
            price=record.price,
            n_available=record.n_available,
            votes=dict(record.votes),
            row_votes=dict(record.row_votes),
            next_price=record.next_price,
            n_available_after=record.n_available_after,
            created_at=now,
        )
    )
    session.add_all(
        Purchase(
            auction_id=auction_id, model_id=model_ids[i], price=price, iteration=record.iteration
        )
        for i, price in record.buyers
    )
    session.add_all(
        Quit(auction_id=auction_id, model_id=model_ids[i], iteration=record.iteration)
        for i in record.quitters
    )
    session.commit()
    return True


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
        if auction is None or auction.status not in UNFINISHED:
            return
        model_ids = [patron.model_id for patron in auction.patrons]
        manifests = _patron_manifests(session, auction.patrons)
    market = _load_market(auction, manifests)
    with database.session(write=True) as session:
        now = utcnow()
        values: dict[str, object] = {"status": "running", "updated_at": now}
        if auction.status == "pending":
            values["started_at"] = now
        if market.finished:  # nothing left to play (a market that ends before its first round)
            values.update(status="finished", finished_at=now)
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
    while not market.finished:
        record = market.step()
        blob = market.checkpoint()
        with database.session(write=True) as session:
            if not _commit_round(session, auction_id, record, blob, model_ids):
                log.warning("auction %d advanced elsewhere; this runner stops", auction_id)
                return


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


class AuctionRunner:
    """Queues auctions onto worker processes and resumes unfinished ones at start-up."""

    def __init__(self, database: Database, context: WorkerContext, *, max_workers: int) -> None:
        self._database = database
        self.pool = WorkerPool(
            name="auction",
            task=run_auction,
            context=context,
            max_workers=max_workers,
            on_exit=self._on_exit,
        )

    def start(self) -> None:
        """Start the pool and queue every auction left pending or running."""
        self.pool.start()
        with self._database.session(write=False) as session:
            unfinished = session.scalars(
                select(Auction.id).where(Auction.status.in_(UNFINISHED)).order_by(Auction.id)
            ).all()
        for auction_id in unfinished:
            log.info("resuming auction %d", auction_id)
            self.pool.submit(auction_id)

    def submit(self, auction_id: int) -> None:
        """Run a newly created auction."""
        self.pool.submit(auction_id)

    def shutdown(self) -> None:
        """Stop the workers; their auctions resume from the last checkpoint at the next start."""
        self.pool.shutdown()

    def _on_exit(self, auction_id: int, exit_code: int | None) -> None:
        """The worker process died in the middle of this auction (killed, crashed)."""
        _mark_failed(
            self._database,
            auction_id,
            f"the auction worker exited (code {exit_code}) before the auction finished",
        )
