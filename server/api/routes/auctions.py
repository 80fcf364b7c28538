"""Auctions: ``POST /auctions`` (operator) starts one in the background, ``GET`` watches it."""

from __future__ import annotations

import dataclasses
from typing import Annotated

from fastapi import APIRouter, Query, Response
from starlette.concurrency import run_in_threadpool

from server.api.deps import (
    AdminDep,
    AuctionRunnerDep,
    NoBodyDep,
    ParticipantTokenDep,
    RoundsDep,
    ServicesDep,
    SessionDep,
    SettingsDep,
    read_in_thread,
)
from server.api.errors import link, responses
from server.api.pages import DEFAULT_PAGE, PageCursor, PageLimit, PageOrder, page_of
from server.api.schemas import (
    AuctionCreate,
    AuctionCreated,
    AuctionIdPath,
    AuctionPage,
    AuctionPublic,
    AuctionSummaryPublic,
    BuyerPublic,
    FineTuneRoundPublic,
    IterationPublic,
    PatronJoin,
    PatronJoined,
    QuitterPublic,
    RoundAnswerPublic,
    Votes,
)
from server.api.schemas.common import IterationPath, ModelIdPath
from server.api.schemas.votes import (
    IterationVotesPublic,
    VotedWeightsPublic,
    VoteExplanationPublic,
)
from server.auctions import service as auctions
from server.auctions.votes import explain_vote, explain_votes, voted_weights
from server.store import crud
from server.store.crud.auctions import HistoryRow
from server.store.status import AnswerOutcome, AuctionStatus, RoundStatus

router = APIRouter(tags=["auctions"])


@router.post(
    "/auctions",
    status_code=201,
    dependencies=[AdminDep],
    operation_id="create_auction",
    responses={
        201: {
            "links": {
                "ReadAuction": link("read_auction", "auction_id", "auction_id"),
                "CancelAuction": link("cancel_auction", "auction_id", "auction_id"),
            }
        },
        **responses(401, 403, 404, 409, 422, 503),
    },
)
def create_auction(
    body: AuctionCreate, session: SessionDep, runner: AuctionRunnerDep, settings: SettingsDep
) -> AuctionCreated:
    """Start an auction (operator). It runs in a worker process; watch it at GET."""
    auction_id = auctions.create_auction(session, runner, body, max_live=settings.max_live_auctions)
    return AuctionCreated(auction_id=auction_id)


def iteration_public(row: HistoryRow | crud.AuctionRound) -> IterationPublic:
    """One committed iteration as ``history`` and the ``iteration`` event show it."""
    return IterationPublic(
        iteration=row.iteration,
        price=row.price,
        n_available=row.n_available,
        votes=Votes(**row.votes),
        row_votes=Votes(**row.row_votes),
        next_price=row.next_price,
        n_available_after=row.n_available_after,
    )


def auction_public(view: crud.AuctionView) -> AuctionPublic:
    """The GET shape of an auction: the fields clients rely on, plus extras."""
    auction = view.auction
    sold = len(view.purchases)
    paid = sum(p.price for p in view.purchases)
    return AuctionPublic(
        id=auction.id,
        status=auction.status,
        iteration=auction.iteration,
        price=auction.price,
        n_available=auction.n_available,
        n_initial=auction.n_initial,
        n_sold=sold,
        history=[iteration_public(row) for row in view.history],
        buyers=[
            BuyerPublic(
                model_id=p.model_id,
                price=p.price,
                iteration=p.iteration,
                participant=p.participant,
                version=p.version,
                version_id=p.version_id,
            )
            for p in view.purchases
        ],
        quitters=[q.model_id for q in view.quitters],
        quitter_details=[
            QuitterPublic(
                model_id=q.model_id,
                participant=q.participant,
                version=q.version,
                iteration=q.iteration,
                version_id=q.version_id,
            )
            for q in view.quitters
        ],
        stop_reason=auction.stop_reason,
        n_patrons=len(view.model_ids),
        model_ids=view.model_ids,
        participants=view.participants,
        revenue=round(paid, 5),
        mean_price=round(paid / sold, 5) if sold else None,
        purchase_rate=sold / auction.n_initial if auction.n_initial else None,
        buyer_fraction=sold / len(view.model_ids) if view.model_ids else None,
        last_price=view.history[-1].price if view.history else None,
        rarity=auction.rarity,
        max_iterations=auction.max_iterations,
        fine_tune=auction.fine_tune,
        seed=auction.seed,
        error=auction.error,
        created_at=auction.created_at,
        started_at=auction.started_at,
        finished_at=auction.finished_at,
        enroll_until=auction.enroll_until,
        fine_tune_mode="remote" if auction.fine_tune_mode == "remote" else "server",
        fine_tune_rounds=auction.fine_tune_rounds if auction.fine_tune else None,
        round_deadline_s=auction.round_deadline_s if auction.fine_tune_mode == "remote" else None,
        buy_fraction="staying" if auction.buy_fraction == "staying" else "all",
        rows=auction.n_rows,
        fine_tuning=[fine_tune_round_public(r) for r in view.fine_tuning],
        current_model_ids=view.current_model_ids,
    )


def fine_tune_round_public(view: crud.RoundView) -> FineTuneRoundPublic:
    """A remote fine-tuning round as ``GET /auctions/{id}`` shows it."""
    answers = [
        RoundAnswerPublic(
            model_id=a.model_id,
            outcome=AnswerOutcome(a.outcome),
            version=a.version,
            version_id=a.version_id,
            uploaded_id=a.uploaded_id,
            bytes_in=a.bytes_in,
            bytes_out=a.bytes_out,
        )
        for a in view.answers
    ]
    return FineTuneRoundPublic(
        round=view.round,
        iteration=view.iteration,
        status=RoundStatus(view.status),
        opened_at=view.opened_at,
        deadline=view.deadline,
        closed_at=view.closed_at,
        bytes_published=view.bytes_published,
        bytes_total=view.bytes_published + sum(a.bytes_in + a.bytes_out for a in answers),
        answers=answers,
    )


@router.get("/auctions/{auction_id}", operation_id="read_auction", responses=responses(404, 422))
async def read_auction(auction_id: AuctionIdPath, session: SessionDep) -> AuctionPublic:
    """Where an auction stands: price, fish left, every committed iteration, buyers, quitters."""
    # One hop to the thread pool for the queries; the response is built on the loop (a sync
    # route would pay a second hop for FastAPI's response validation).
    view = await read_in_thread(auctions.read_auction, session, auction_id)
    return auction_public(view)


@router.delete(
    "/auctions/{auction_id}",
    dependencies=[AdminDep, NoBodyDep],
    operation_id="cancel_auction",
    responses=responses(401, 403, 404, 409, 422),
)
async def cancel_auction(
    auction_id: AuctionIdPath,
    session: SessionDep,
    runner: AuctionRunnerDep,
    watcher: RoundsDep,
    services: ServicesDep,
) -> AuctionPublic:
    """Cancel a pending or running auction (operator): status ``cancelled``, its committed
    rounds, buyers and quitters kept, its open fine-tuning round closed, its worker stopped;
    the agents waiting on its rounds are answered at once. An ended auction is 409. Uploads
    its round holds that no request waits for any more are judged after the answer."""
    view = await run_in_threadpool(auctions.cancel_auction, session, runner, auction_id)
    watcher.poke(auction_id)
    services.judge_left_pending(auction_id)
    return auction_public(view)


@router.post(
    "/auctions/{auction_id}/patrons",
    status_code=201,
    operation_id="join_auction",
    responses={
        200: {"description": "The model had joined before", "model": PatronJoined},
        **responses(401, 403, 404, 409, 422),
    },
)
def join_auction(
    auction_id: AuctionIdPath,
    body: PatronJoin,
    session: SessionDep,
    token: ParticipantTokenDep,
    response: Response,
) -> PatronJoined:
    """Add one of your accepted models to an enrolling auction's patrons (its participant's
    token), while its enrollment lasts (``enrollment_s`` at its creation): one model per
    participant. 201, or 200 for the same model again; 409 once the enrollment is over."""
    enrollment, position, new = auctions.join_auction(session, auction_id, body.model_id, token)
    if not new:
        response.status_code = 200
    return PatronJoined(
        auction_id=auction_id,
        model_id=body.model_id,
        position=position,
        n_patrons=len(enrollment.patrons),
        enroll_until=enrollment.enroll_until,
    )


@router.get("/auctions", operation_id="list_auctions", responses=responses(422))
async def list_auctions(
    session: SessionDep,
    limit: PageLimit = DEFAULT_PAGE,
    cursor: PageCursor = None,
    status: Annotated[
        AuctionStatus | None, Query(description="Only auctions in this status.")
    ] = None,
    order: PageOrder = "newest",
) -> AuctionPage:
    """Auctions, newest (or oldest) first, a page at a time (follow ``next_cursor``)."""
    rows = await read_in_thread(
        crud.list_auctions, session, before=cursor, limit=limit + 1, status=status, order=order
    )
    items, next_cursor = page_of(rows, limit)
    return AuctionPage(
        items=[
            AuctionSummaryPublic(**dataclasses.asdict(row), n_sold=row.n_initial - row.n_available)
            for row in items
        ],
        next_cursor=next_cursor,
    )


@router.get(
    "/auctions/{auction_id}/iterations/{iteration}/votes",
    operation_id="explain_votes",
    responses=responses(404, 422),
)
async def read_votes(
    auction_id: AuctionIdPath, iteration: IterationPath, session: SessionDep
) -> IterationVotesPublic:
    """Every patron's vote in one committed iteration, with the neurons behind each (as
    ``.../votes/{model_id}`` gives one): who bought, held and quit, and why. 404 for an
    unknown auction or an uncommitted iteration."""
    return await read_in_thread(explain_votes, session, auction_id, iteration)


@router.get(
    "/auctions/{auction_id}/iterations/{iteration}/votes/{model_id}",
    operation_id="explain_vote",
    responses=responses(404, 422),
)
async def read_vote(
    auction_id: AuctionIdPath, iteration: IterationPath, model_id: ModelIdPath, session: SessionDep
) -> VoteExplanationPublic:
    """Why a patron voted buy, hold or quit in one committed iteration: its external sensor
    (PG, SZ, LSR, ST), decision logits (B, L, Q) and the PFC's verdicts (T, F) on row 0, the
    row that decides. 404 for an unknown auction, an uncommitted iteration, or a model that
    did not vote in it (patrons leave once they buy or quit)."""
    return await read_in_thread(explain_vote, session, auction_id, iteration, model_id)


@router.get(
    "/auctions/{auction_id}/iterations/{iteration}/votes/{model_id}/weights",
    operation_id="voted_weights",
    responses=responses(404, 422),
)
async def read_voted_weights(
    auction_id: AuctionIdPath, iteration: IterationPath, model_id: ModelIdPath, session: SessionDep
) -> VotedWeightsPublic:
    """The weights that cast a patron's vote in one committed iteration, as a manifest: its
    version's, or those a server-mode auction had fine-tuned it to inside the market by then
    (``fine_tuned_after`` names the iteration). The same 404s as ``.../votes/{model_id}``."""
    return await read_in_thread(voted_weights, session, auction_id, iteration, model_id)
