"""Participants: ``GET /participants/{name}``, who submitted under a name, its versions and the
auctions they entered; ``POST /participants/{name}/token``, a new token for it."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path
from starlette.concurrency import run_in_threadpool

from agents.manifest import Participant
from server.api.deps import (
    NoBodyDep,
    ParticipantTokenDep,
    ServicesDep,
    SessionDep,
    read_in_thread,
)
from server.api.errors import responses
from server.api.pages import MAX_PAGE
from server.api.routes.models import model_summary
from server.api.schemas import EntryPublic, ParticipantPublic, TokenRotated
from server.api.schemas.models import EntryOutcome
from server.store import crud
from server.store.status import AuctionStatus
from server.submissions import service as models

STILL_IN: dict[AuctionStatus, EntryOutcome] = {
    AuctionStatus.PENDING: "joined",
    AuctionStatus.RUNNING: "bidding",
    AuctionStatus.FINISHED: "stayed",
    AuctionStatus.CANCELLED: "stopped",
    AuctionStatus.FAILED: "stopped",
}
"""A patron that neither bought nor quit, by its auction's status."""

router = APIRouter(tags=["participants"])


@router.get("/participants/{name}", operation_id="read_participant", responses=responses(404, 422))
async def read_participant(
    name: Annotated[Participant, Path(description="A participant's name.")], session: SessionDep
) -> ParticipantPublic:
    """A participant with its newest versions (up to a page; ``GET /models?participant=`` pages
    through all of them), how many it has, and the newest auctions its models entered (up to a
    page), each with how its patron left it."""
    view = await read_in_thread(models.read_participant, session, name, limit=MAX_PAGE)
    return ParticipantPublic(
        name=view.name,
        created_at=view.created_at,
        n_versions=view.n_versions,
        versions=[model_summary(row) for row in view.versions],
        auctions=[_entry(entry) for entry in view.entries],
    )


@router.post(
    "/participants/{name}/token",
    operation_id="rotate_token",
    responses=responses(401, 403, 404, 422),
)
async def rotate_token(
    name: Annotated[Participant, Path(description="A participant's name, as registered.")],
    session: SessionDep,
    token: ParticipantTokenDep,
    services: ServicesDep,
    _: Annotated[None, NoBodyDep],
) -> TokenRotated:
    """A new token for the participant, with its current token (one that may have leaked) or
    the operator's (a participant that lost its token): the old token is refused from now on,
    for every request that needs it."""
    participant, fresh = await run_in_threadpool(
        models.rotate_token, session, name, token=token, admin_hash=services.admin_token_hash
    )
    return TokenRotated(participant=participant, token=fresh)


def _entry(entry: crud.Entry) -> EntryPublic:
    status = AuctionStatus(entry.status)
    outcome: EntryOutcome
    if entry.bought_at is not None:
        outcome, iteration = "bought", entry.bought_in
    elif entry.quit_in is not None:
        outcome, iteration = "quit", entry.quit_in
    else:
        outcome, iteration = STILL_IN[status], None
    return EntryPublic(
        auction_id=entry.auction_id,
        auction_status=status,
        model_id=entry.model_id,
        bidding_model_id=entry.bidding_id or entry.model_id,
        outcome=outcome,
        price=entry.bought_at,
        iteration=iteration,
    )
