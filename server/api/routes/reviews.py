"""Human review: ``GET /reviews`` (the held models, operator), ``POST /models/{id}/review`` (an
inspector's decision, operator) and ``POST /models/{id}/appeal`` (the model's participant)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from pydantic import BeforeValidator
from starlette.concurrency import run_in_threadpool

from server.api.deps import AdminDep, BearerDep, SessionDep, SettingsDep, read_in_thread
from server.api.errors import responses
from server.api.pages import DEFAULT_PAGE, PageLimit, page_of
from server.api.routes.models import review_entries, verdict_name
from server.api.schemas import (
    MAX_ROW_ID,
    AppealCreate,
    EvidencePublic,
    HeldModelPublic,
    HeldPage,
    LaterVersionPublic,
    ModelIdPath,
    ReasonPublic,
    ReviewCreate,
    ReviewedPublic,
)
from server.api.schemas.common import digits_only
from server.store import crud
from server.store.status import ModelStatus, ReviewDecision
from server.submissions import reviews

router = APIRouter(tags=["reviews"])

ReviewCursor = Annotated[
    int | None,
    Query(
        ge=1,
        le=MAX_ROW_ID,
        description="The ``next_cursor`` of the previous page (the page holds the held models "
        "above that id, oldest first); omit for the first page.",
    ),
    BeforeValidator(digits_only),  # an id, written as path ids are
]


def _reviewed(row: crud.StoredModel) -> ReviewedPublic:
    return ReviewedPublic(
        model_id=row.id,
        status=ModelStatus(row.status),
        verdict=verdict_name(row.status),
        accepted=row.accepted,
        reviews=review_entries(row),
    )


@router.get(
    "/reviews",
    operation_id="list_reviews",
    dependencies=[AdminDep],
    responses=responses(401, 403, 422),
)
async def list_reviews(
    session: SessionDep,
    settings: SettingsDep,
    limit: PageLimit = DEFAULT_PAGE,
    cursor: ReviewCursor = None,
) -> HeldPage:
    """The models held for an inspector (operator), oldest first, each with the screener's
    reasons and evidence; ``cursor`` is the ``next_cursor`` of the previous page (ids above
    it)."""
    rows = await read_in_thread(crud.held_models, session, after=cursor, limit=limit + 1)
    items, next_cursor = page_of(rows, limit)
    return HeldPage(
        items=[
            HeldModelPublic(
                id=row.id,
                participant=row.participant,
                version=row.version,
                reasons=[ReasonPublic.model_validate(r) for r in row.reasons],
                evidence=[EvidencePublic.model_validate(e) for e in row.evidence or []],
                created_at=row.created_at,
                auction_id=row.auction_id,
                round=row.round,
                appeal=row.appeal,
                later_versions=[
                    LaterVersionPublic(model_id=model_id, version=version, status=status)
                    for model_id, version, status in row.newer
                ],
            )
            for row in items
        ],
        next_cursor=next_cursor,
        review_margin=settings.review_margin,
    )


@router.post(
    "/models/{model_id}/review",
    operation_id="review_model",
    dependencies=[AdminDep],
    responses=responses(401, 403, 404, 409, 422),
)
async def review_model(
    model_id: ModelIdPath, body: ReviewCreate, session: SessionDep
) -> ReviewedPublic:
    """An inspector's decision on a held model (operator): ``admit`` makes it accepted (it may
    enter auctions), ``refuse`` refused; recorded in its audit log with the evidence seen. A
    model that is not held → 409."""
    row = await run_in_threadpool(
        reviews.decide,
        session,
        model_id,
        decision=ReviewDecision(body.decision),
        inspector=body.inspector,
        note=body.note,
    )
    return _reviewed(row)


@router.post(
    "/models/{model_id}/appeal",
    operation_id="appeal_model",
    responses=responses(401, 403, 404, 409, 422, 429),
)
async def appeal_model(
    model_id: ModelIdPath,
    body: AppealCreate,
    session: SessionDep,
    credentials: BearerDep,
    settings: SettingsDep,
    request: Request,
) -> ReviewedPublic:
    """Send a model the screener refused to the review queue (its participant's token): it is
    held until an inspector decides. Once per model: a second appeal, a model accepted, held
    or refused by an inspector → 409; past SRD_QUOTA_ADDRESS_APPEALS_PER_DAY appeals from one
    address → 429."""
    row = await run_in_threadpool(
        reviews.appeal,
        session,
        model_id,
        token=None if credentials is None else credentials.credentials,
        note=body.note,
        address=request.client.host if request.client is not None else None,
        per_day=settings.quota_address_appeals_per_day,
    )
    return _reviewed(row)
