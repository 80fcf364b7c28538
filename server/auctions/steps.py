"""Auctions as a state machine in the database, moved by short steps in worker processes.

An auction's row says where it stands (status, iteration, price, supply, the market checkpoint
with its random state and fine-tuned weights) and when its next step is due
(``next_step_at``). The runner (``server.work.runner``) claims a due auction under a lease and hands
it to a worker process, which runs ONE step (``run_step``):

1. restore the market from the last committed checkpoint;
2. if the checkpoint awaits a remote fine-tuning round and the round is still open: stop at
   once unless every asked patron has answered or the deadline has passed (the auction is then
   due again at the deadline, plus half a second for uploads that arrived in time to be
   stored); else judge the uploads still pending and close the round. Then
   apply the closed round's accepted versions;
3. play iterations until the auction ends or opens a fine-tuning round, or has played for
   ``STEP_SLICE_S`` (then it is due again at once, and takes its turn), committing each
   iteration in ONE transaction: its row, purchases and quits, the new price and supply, the
   checkpoint, the round it opens (rows, seeds, asked patrons, absolute deadline) and when the
   next step is due (now while it plays; the deadline plus ``CLOSE_GRACE`` while a round is
   open; never once ended).

An open round holds no process and no thread: the API stores the uploads and their verdicts
(``server.auctions.uploads``), and the verdict that judges the last asked patron's upload
closes the round in its own transaction and makes the auction due at once. Every commit is
conditional on the auction still standing where the step found it (status running, the
iteration expected, the round still open), so a stale or duplicated step never writes twice,
and a cancelled auction is never moved again. A step that dies (``kill -9``) loses at most the
iteration in flight: the auction is still due and the next step resumes from the checkpoint,
bit-identically. An auction whose stored state cannot be continued is failed with the reason.
"""

from __future__ import annotations

import functools
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import TYPE_CHECKING

from sqlalchemy.orm import Session

from agents.manifest import Manifest, parse_manifest
from server.store import crud
from server.store.crud.steps import (
    CLOSE_GRACE,
    IterationRow,
    MovedOnError,
    NewRound,
    PendingUploadsError,
    StepRound,
)
from server.store.db import DATABASE_RETRY_AFTER_S, Database, JSONText, is_database_outage
from server.store.status import AUCTION_UNFINISHED, AuctionStatus
from server.store.tables import Auction, utcnow
from server.submissions import quotas
from server.work.pool import WorkerContext, error_summary
from server.work.runner import WorkKind
from sim.market import MarketConfig, fish_on_sale

if TYPE_CHECKING:
    from agents.batch import FSNBatch
    from sim.market import FineTuneRound, Market, RescreenBatch
    from sim.market.engine import Refusal

log = logging.getLogger("srd.auctions")

CLOSE_TRIES = 3
"""Times a step judges a round's pending uploads and tries to close it (an upload in time may
be stored while the step judges the others)."""


class ResumeError(RuntimeError):
    """The auction's stored state cannot be continued."""


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
        n_rows=auction.n_rows,
    )


def rescreening(margin: float) -> RescreenBatch:
    """The re-screening of a server-mode auction's fine-tuned patrons: a new version bids only
    when the screener accepts it by more than ``margin`` (``screener.review``), as a remote
    upload does: one it would hold for an inspector does not bid, its previous version does.
    So faithful remote agents replay a server-mode auction exactly. A version not kept
    carries the screener's reasons (those that hold it, when held), as the auction keeps
    them."""
    from screener import judge, review, with_hold_reasons

    def keeps(patrons: FSNBatch) -> list[bool | Refusal]:
        judged: list[bool | Refusal] = []
        for verdict in judge(patrons, at_the_door=False):
            if review(verdict, margin) == "accepted":
                judged.append(True)
            else:  # refused, or held: the reasons that hold it too
                reasons = with_hold_reasons(verdict, margin).reasons
                judged.append([reason.to_dict() for reason in reasons])
        return judged

    return keeps


STEP_SLICE_S = 2.0
"""A step that plays on ends after the iteration it commits once it has played this long (the
auction stays due, and is claimed again in its turn): a long server-mode auction takes turns
with the other auctions' steps instead of holding a worker for its whole life."""
ENTERED_KEPT = 1024
"""Parsed manifests of entered versions a worker process keeps between steps (16 auctions of
64 patrons): stored versions never change, and parsing an auction's 64 at every step cost more
than the rest of the step's reads."""


@dataclass
class _Kept:
    """What a worker process keeps of one database from one step to the next: the database
    (its connections and its compiled statements: a first read of an auction's state costs
    tens of milliseconds more than the next ones) and the entered manifests parsed there."""

    database: Database
    entered: dict[int, Manifest] = field(default_factory=dict)

    def manifests(self, session: Session, model_ids: list[int]) -> list[Manifest]:
        """The patrons' entered manifests, in order (parsed once; past ``ENTERED_KEPT``, the
        others are forgotten, never this auction's: it may hold more than that alone)."""
        wanted = list(dict.fromkeys(model_ids))
        missing = [model_id for model_id in wanted if model_id not in self.entered]
        if missing:
            if len(self.entered) + len(missing) > ENTERED_KEPT:
                self.entered = {m: self.entered[m] for m in wanted if m in self.entered}
            stored = crud.patron_manifests(session, model_ids=missing)
            self.entered.update(zip(missing, map(parse_manifest, stored), strict=True))
        return [self.entered[model_id] for model_id in model_ids]


@functools.cache
def _kept(url: str) -> _Kept:
    """This process's ``_Kept`` of the database at ``url`` (a database replaced there is
    refused by it, as by the API, until a restart)."""
    return _Kept(Database(url))


def _load_market(auction: Auction, manifests: Sequence[Manifest], margin: float) -> Market:
    # The market (and torch) is imported here, in the worker: the API process imports this
    # module for its work kind and never plays an auction itself.
    from sim.market import Market

    config = _market_config(auction)
    server_mode = auction.fine_tune and config.fine_tune_mode == "server"
    judge = rescreening(margin) if server_mode else None
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


@dataclass(frozen=True)
class _Played:
    """An iteration played and made ready to write (its row, the market's checkpoint, the
    round it opens), computed before the write transaction: on SQLite that transaction holds
    the one write lock, which the API's uploads wait for."""

    row: IterationRow
    checkpoint: bytes
    opens: FineTuneRound | None


def _play(market: Market, model_ids: list[int]) -> _Played:
    """The market's next iteration, played and made ready to write."""
    record = market.step()
    explained = record.explained()["patrons"]
    row = IterationRow(
        iteration=record.iteration,
        price=record.price,
        n_available=record.n_available,
        votes=dict(record.votes),
        row_votes=dict(record.row_votes),
        next_price=record.next_price,
        n_available_after=record.n_available_after,
        finished=record.finished,
        stop_reason=record.stop_reason,
        explanations=JSONText(
            json.dumps(
                {
                    "row": record.row,
                    "patrons": [
                        {**vote, "model_id": model_ids[vote["patron"]]} for vote in explained
                    ],
                }
            )
        ),
        buyers=[(model_ids[i], price) for i, price in record.buyers],
        quitters=[model_ids[i] for i in record.quitters],
        tuned=[
            (model_ids[i], JSONText(market.current_manifest(i).model_dump_json()))
            for i in record.fine_tuned
        ],
        refused=[
            (model_ids[i], why) for i, why in zip(record.reverted, record.refusals, strict=True)
        ],
    )
    return _Played(row, market.checkpoint(), market.pending_round)


def _commit_iteration(
    session: Session, auction: Auction, played: _Played, now: datetime
) -> StepRound | None:
    """Write one iteration played at ``now``, with the round it opens (returned, if any)."""
    pending = played.opens
    opened = None
    if pending is not None:
        opened = NewRound(
            round=pending.iteration + 1,
            iteration=pending.iteration,
            rows=pending.rows.tolist(),
            fine_tune_seed=pending.fine_tune_seed,
            augmentation_seed=pending.augmentation_seed,
            asked=list(pending.patrons),
            deadline=now + timedelta(seconds=auction.round_deadline_s),
        )
    return crud.commit_iteration(
        session,
        auction_id=auction.id,
        row=played.row,
        checkpoint=played.checkpoint,
        opened=opened,
        now=now,
    )


def _judge_pending(database: Database, round_id: int, margin: float) -> None:
    """Judge the round's uploads whose verdict the API never recorded (its screener was down,
    or it died): they came in time, so they count (held within ``margin`` of a bar), and each
    verdict counts for its participant's cooldown as the API's would (its address, which the
    API alone knew, is not charged)."""
    with database.session(write=False) as session:
        pending = crud.pending_uploads(session, round_id=round_id)
    if not pending:
        return
    from screener import rescreen_many

    manifests = [parse_manifest(upload.manifest) for upload in pending]
    verdicts = rescreen_many(manifests)
    with database.session(write=True) as session:
        connection, now = session.connection(), utcnow()
        for upload, manifest, verdict in zip(pending, manifests, verdicts, strict=True):
            recorded = crud.record_verdict(
                connection, answer_id=upload.answer_id, verdict=verdict, margin=margin, now=now
            )
            if recorded.judged:
                quotas.record_round_upload(
                    connection,
                    participant=manifest.participant,
                    address=None,
                    accepted=recorded.accepted,
                    now=now,
                )
        session.commit()


def _fail(database: Database, auction_id: int, reason: str) -> None:
    log.warning("auction %d failed: %s", auction_id, reason)
    with database.session(write=True) as session:
        crud.fail_unfinished(session, table=Auction, row_id=auction_id, error=reason)
        session.commit()


def _not_yet(database: Database, auction_id: int, row: StepRound) -> bool:
    """An open round that may still hear answers: the auction is due again at its deadline,
    plus ``CLOSE_GRACE`` for uploads that arrived in time to be stored (True); False when the
    round can close now."""
    with database.session(write=False) as session:
        answered = crud.answered(session, round_id=row.id)
    if answered >= len(row.asked) or utcnow() >= row.deadline + CLOSE_GRACE:
        return False
    with database.session(write=True) as session:
        crud.due_at(session, auction_id=auction_id, when=row.deadline + CLOSE_GRACE)
        session.commit()
    return True


def _close(database: Database, auction_id: int, row: StepRound, margin: float) -> None:
    """Close the open round (after judging the uploads still pending): its silent patrons
    marked missing, its accepted versions bidding. An upload in time may be stored while the
    step judges the others: then again. Closed meanwhile (its last verdict, a cancel): done."""
    for attempt in range(CLOSE_TRIES):
        _judge_pending(database, row.id, margin)
        with database.session(write=True) as session:
            try:
                crud.close_round(
                    session.connection(),
                    auction_id=auction_id,
                    round_id=row.id,
                    asked=row.asked,
                    now=utcnow(),
                )
            except PendingUploadsError:
                if attempt + 1 == CLOSE_TRIES:
                    raise
                continue
            session.commit()
            return


def _end_enrollment(database: Database, auction_id: int) -> bool:
    """Fix the patrons of an auction whose enrollment is over (its supply too, for a rarity);
    False when it cannot start: its enrollment lasts a while yet (due again then), or nobody
    joined, or too few for a single fish (failed, saying so)."""
    with database.session(write=True) as session:
        enrollment = crud.lock_enrollment(session, auction_id=auction_id)
        if (
            enrollment is None
            or enrollment.status != AuctionStatus.PENDING
            or enrollment.enroll_until is None
        ):
            return True  # gone, ended or started meanwhile (a cancel, another step)
        if utcnow() < enrollment.enroll_until:  # woken early (another replica's clock)
            crud.due_at(session, auction_id=auction_id, when=enrollment.enroll_until)
            session.commit()
            return False
        patrons = len(enrollment.patrons)
        rarity = enrollment.rarity
        n_fish = None if rarity is None else fish_on_sale(patrons, rarity=rarity)
        problem = None
        if patrons == 0:
            problem = "nobody joined before its enrollment ended"
        elif n_fish is not None and n_fish < 1:
            problem = f"rarity {rarity} × {patrons} patrons puts no fish on sale"
        crud.end_enrollment(session, auction_id=auction_id, n_fish=None if problem else n_fish)
        if problem is not None:
            crud.fail_unfinished(session, table=Auction, row_id=auction_id, error=problem)
        session.commit()
    if problem is not None:
        log.warning("auction %d failed: %s", auction_id, problem)
    return problem is None


def _step(kept: _Kept, auction_id: int, margin: float) -> None:
    database = kept.database
    # Read and rebuild the market outside any write transaction (parsing the manifests and
    # building the market take a while; on SQLite a write transaction holds the one write lock).
    with database.session(write=False) as session:
        state = crud.step_state(session, auction_id=auction_id)
        if state is None or state[0].status not in AUCTION_UNFINISHED:
            return
        auction, row = state
        enrolling = auction.status == AuctionStatus.PENDING and auction.enroll_until is not None
        if not enrolling:
            model_ids = [patron.model_id for patron in auction.patrons]
            manifests = kept.manifests(session, model_ids)
    if enrolling:  # its patrons fixed first, then read again
        if _end_enrollment(database, auction_id):
            _step(kept, auction_id, margin)
        return
    if row is not None and row.open and _not_yet(database, auction_id, row):
        return
    market = _load_market(auction, manifests, margin)
    if auction.status == AuctionStatus.PENDING:
        with database.session(write=True) as session:
            crud.start(session, auction_id=auction_id, finished=market.finished, now=utcnow())
            session.commit()
        if market.finished:
            return
    if market.pending_round is not None:
        number = market.pending_round.iteration + 1
        if row is None or row.round != number:
            raise ResumeError(f"the checkpoint awaits fine-tuning round {number}, never opened")
        if row.open:
            _close(database, auction_id, row, margin)
        with database.session(write=False) as session:
            accepted = crud.accepted_uploads(session, round_id=row.id)
        market.apply_round({p: parse_manifest(m) for p, (_, m) in accepted.items()})
    playing = time.monotonic()
    while not market.finished:
        began = utcnow()  # the iteration is computed before the write lock is taken
        played = _play(market, model_ids)
        with database.session(write=True) as session:
            opened = _commit_iteration(session, auction, played, began)
            session.commit()
        if opened is not None:
            return
        if not market.finished and time.monotonic() - playing > STEP_SLICE_S:
            return  # due now: the next step resumes from this commit, after the others' turns
    log.info("auction %d finished (%s)", auction_id, market.stop_reason)


def run_step(context: WorkerContext, auction_id: int) -> None:
    """Worker process entry point: one step of the auction (see the module docstring)."""
    kept = _kept(context.database_url)
    database = kept.database
    try:
        _step(kept, auction_id, context.review_margin)
    except MovedOnError:
        log.info(
            "auction %d moved on without this step (cancelled, or stepped elsewhere)", auction_id
        )
    except ResumeError as exc:
        _fail(database, auction_id, f"cannot resume: {exc}")
    except Exception as exc:
        if is_database_outage(exc):  # nothing committed: the auction stays due, and is retried
            log.warning("auction %d: step not committed, database unavailable: %s", auction_id, exc)
            return
        # Readers of the auction get the exception's line; the log keeps its frames too.
        log.warning("auction %d: step failed: %s", auction_id, error_summary(exc))
        _fail(database, auction_id, error_summary(exc).split("\nTraceback", 1)[0])


def _nothing_to_prepare(session: Session, auction_ids: list[int]) -> None:
    """Claimed auctions need nothing: their step resumes from the last checkpoint."""


def _give_back_round_time(session: Session, began: datetime, now: datetime) -> None:
    """After a database outage (from ``began`` at the earliest to ``now``): patrons may not
    have heard of an open round, or had their uploads refused, all along; its deadline moves
    so that they have the time it had left when the outage began, from when they were told
    to try again (``DATABASE_RETRY_AFTER_S`` from now)."""
    retry = timedelta(seconds=DATABASE_RETRY_AFTER_S)
    moved, already = crud.push_back_deadlines(session, began=began, now=now, retry=retry)
    if moved:
        log.warning(
            "after a database outage of up to %.1f s: the open rounds of auctions %s get the "
            "time they had left back",
            (now - began).total_seconds(),
            ", ".join(map(str, moved)),
        )
    if already:
        log.info(
            "after a database outage of up to %.1f s: the open rounds of auctions %s were "
            "given their time back by another replica",
            (now - began).total_seconds(),
            ", ".join(map(str, already)),
        )


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
    progress=Auction.iteration,
    after_outage=_give_back_round_time,
)
"""Auctions as background work (``server.work.runner``): a claim runs one step."""
