"""Auctions: ``POST /auctions`` (operator) starts one in the background, ``GET`` watches it."""

from __future__ import annotations

import dataclasses
from typing import cast

from fastapi import APIRouter, HTTPException, Request
from starlette.concurrency import run_in_threadpool

from server import crud
from server.auctions import AuctionRunner, base_price
from server.db import SessionDep
from server.errors import api_error, error_item, link, responses
from server.pages import DEFAULT_PAGE, PageCursor, PageLimit, page_of
from server.schemas import (
    AuctionCreate,
    AuctionCreated,
    AuctionIdPath,
    AuctionPage,
    AuctionPublic,
    AuctionSummaryPublic,
    BuyerPublic,
    FineTuneRoundPublic,
    IterationPublic,
    RoundAnswerPublic,
    RoundOutcome,
    Votes,
)
from server.security import AdminDep

router = APIRouter(tags=["auctions"])


def _patron_ids(session: SessionDep, body: AuctionCreate) -> list[int]:
    """The ordered patron list: the given ids (each must exist, 404, and be accepted, 409), or
    by default the newest accepted version of every participant (409 while there is none)."""
    if body.model_ids is None:
        ids = [row.id for row in crud.latest_accepted_models(session)]
        if not ids:
            raise api_error(
                409,
                "no accepted model exists yet: submit models first",
                loc=("body", "model_ids"),
                kind="no_patrons",
            )
        return ids
    found = crud.get_models(session, model_ids=body.model_ids)
    missing = [
        error_item(
            f"model {model_id} does not exist", loc=("body", "model_ids", i), kind="not_found"
        )
        for i, model_id in enumerate(body.model_ids)
        if model_id not in found
    ]
    if missing:
        raise HTTPException(404, detail=missing)
    rejected = [
        error_item(
            f"model {model_id} was rejected by the screener and cannot enter an auction",
            loc=("body", "model_ids", i),
            kind="rejected",
        )
        for i, model_id in enumerate(body.model_ids)
        if not found[model_id].accepted
    ]
    if rejected:
        raise HTTPException(409, detail=rejected)
    return list(body.model_ids)


def _require_one_supply_option(body: AuctionCreate) -> None:
    if (body.n_fish is None) == (body.rarity is None):
        loc = ("body", "n_fish") if body.n_fish is not None else ("body", "rarity")
        raise api_error(
            422, "give exactly one of n_fish or rarity", loc=loc, kind="n_fish_xor_rarity"
        )


def _remote_fine_tuning(body: AuctionCreate) -> bool:
    """Whether the participants fine-tune (remote); refuses settings that contradict it."""
    remote = body.fine_tune_mode == "remote"
    if remote and "fine_tune" in body.model_fields_set and not body.fine_tune:
        raise api_error(
            422,
            "a remote auction fine-tunes: leave fine_tune out or set it true",
            loc=("body", "fine_tune"),
            kind="remote_fine_tune",
        )
    if not remote and "round_deadline_s" in body.model_fields_set:
        raise api_error(
            422,
            'round_deadline_s applies to fine_tune_mode "remote" only',
            loc=("body", "round_deadline_s"),
            kind="remote_only",
        )
    return remote


def _fish_count(body: AuctionCreate, n_patrons: int) -> int:
    """n_fish as given, or int(rarity × patrons) (truncation, as the reference)."""
    if body.n_fish is not None:
        return body.n_fish
    assert body.rarity is not None
    n_fish = int(body.rarity * n_patrons)
    if n_fish < 1:
        raise api_error(
            409,
            f"rarity {body.rarity} × {n_patrons} patrons puts no fish on sale",
            loc=("body", "rarity"),
            kind="no_fish",
        )
    return n_fish


@router.post(
    "/auctions",
    status_code=201,
    dependencies=[AdminDep],
    operation_id="create_auction",
    responses={
        201: {"links": {"ReadAuction": link("read_auction", "auction_id", "auction_id")}},
        **responses(401, 403, 404, 409, 422),
    },
)
def create_auction(body: AuctionCreate, session: SessionDep, request: Request) -> AuctionCreated:
    """Start an auction (operator). It runs in a worker process; watch it at GET."""
    _require_one_supply_option(body)
    remote = _remote_fine_tuning(body)
    patron_ids = _patron_ids(session, body)
    auction = crud.create_auction(
        session,
        model_ids=patron_ids,
        n_fish=_fish_count(body, len(patron_ids)),
        rarity=body.rarity,
        max_iterations=body.max_iterations,
        fine_tune=body.fine_tune or remote,
        seed=body.seed,
        opening_price=base_price(),
        fine_tune_mode=body.fine_tune_mode,
        fine_tune_rounds=body.fine_tune_rounds,
        round_deadline_s=body.round_deadline_s,
    )
    session.commit()
    runner: AuctionRunner = request.app.state.auctions
    runner.submit(auction.id)
    return AuctionCreated(auction_id=auction.id)


def auction_public(view: crud.AuctionView) -> AuctionPublic:
    """The GET shape of an auction: the fields clients rely on, plus extras."""
    auction = view.auction
    return AuctionPublic(
        id=auction.id,
        status=auction.status,
        iteration=auction.iteration,
        price=auction.price,
        n_available=auction.n_available,
        n_initial=auction.n_initial,
        history=[
            IterationPublic(
                iteration=row.iteration,
                price=row.price,
                n_available=row.n_available,
                votes=Votes(**row.votes),
                row_votes=Votes(**row.row_votes),
                next_price=row.next_price,
                n_available_after=row.n_available_after,
            )
            for row in view.history
        ],
        buyers=[
            BuyerPublic(model_id=p.model_id, price=p.price, iteration=p.iteration)
            for p in view.purchases
        ],
        quitters=view.quitters,
        stop_reason=auction.stop_reason,
        n_patrons=len(view.model_ids),
        model_ids=view.model_ids,
        revenue=round(sum(p.price for p in view.purchases), 5),
        rarity=auction.rarity,
        max_iterations=auction.max_iterations,
        fine_tune=auction.fine_tune,
        seed=auction.seed,
        error=auction.error,
        created_at=auction.created_at,
        started_at=auction.started_at,
        finished_at=auction.finished_at,
        fine_tune_mode="remote" if auction.fine_tune_mode == "remote" else "server",
        fine_tune_rounds=auction.fine_tune_rounds,
        round_deadline_s=auction.round_deadline_s,
        fine_tuning=[fine_tune_round_public(r) for r in view.fine_tuning],
        current_model_ids=view.current_model_ids,
    )


def fine_tune_round_public(view: crud.RoundView) -> FineTuneRoundPublic:
    """A remote fine-tuning round as ``GET /auctions/{id}`` shows it."""
    answers = [
        RoundAnswerPublic(
            model_id=a.model_id,
            outcome=cast(RoundOutcome, a.outcome),
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
        status="open" if view.status == "open" else "closed",
        opened_at=view.opened_at,
        deadline=view.deadline,
        closed_at=view.closed_at,
        bytes_published=view.bytes_published,
        bytes_total=view.bytes_published + sum(a.bytes_in + a.bytes_out for a in answers),
        answers=answers,
    )


@router.get("/auctions/{auction_id}", operation_id="read_auction", responses=responses(404, 422))
async def read_auction(auction_id: AuctionIdPath, session: SessionDep) -> AuctionPublic:
    """Where an auction stands: price, fish left, every committed round, buyers, quitters."""
    # One hop to the thread pool for the queries; the response is built on the loop (a sync
    # route would pay a second hop for FastAPI's response validation).
    view = await run_in_threadpool(crud.get_auction, session, auction_id=auction_id)
    if view is None:
        raise api_error(
            404,
            f"auction {auction_id} does not exist",
            loc=("path", "auction_id"),
            kind="not_found",
        )
    return auction_public(view)


@router.get("/auctions", operation_id="list_auctions", responses=responses(422))
async def list_auctions(
    session: SessionDep, limit: PageLimit = DEFAULT_PAGE, cursor: PageCursor = None
) -> AuctionPage:
    """Auctions, newest first, a page at a time (follow ``next_cursor``)."""
    rows = await run_in_threadpool(crud.list_auctions, session, before=cursor, limit=limit + 1)
    items, next_cursor = page_of(rows, limit)
    return AuctionPage(
        items=[
            AuctionSummaryPublic(**dataclasses.asdict(row), n_sold=row.n_initial - row.n_available)
            for row in items
        ],
        next_cursor=next_cursor,
    )
