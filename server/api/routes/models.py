"""Models: ``POST /submit`` stores a screened manifest version, ``GET /models/{id}`` reads one."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from pydantic import BeforeValidator

from agents.manifest import Manifest, Participant
from server.api.deps import (
    BearerDep,
    ScreeningDep,
    SessionDep,
    SettingsDep,
    SubmissionsDep,
    read_in_thread,
)
from server.api.errors import link, responses
from server.api.pages import DEFAULT_PAGE, PageCursor, PageLimit, page_of
from server.api.schemas import (
    MAX_LISTED_AUCTIONS,
    EvidencePublic,
    ModelIdPath,
    ModelPage,
    ModelPublic,
    ModelSummaryPublic,
    ReasonPublic,
    ReviewPublic,
    SubmitPublic,
    VerdictName,
)
from server.api.schemas.common import true_or_false
from server.store import crud
from server.store.status import ModelStatus
from server.submissions import service as models

router = APIRouter(tags=["models"])


def _reasons(row: crud.StoredModel) -> list[ReasonPublic]:
    return [ReasonPublic.model_validate(reason) for reason in row.reasons]


@router.post(
    "/submit",
    status_code=201,
    operation_id="submit",
    # A first submission needs no token: the bearer is optional (either scheme or none).
    openapi_extra={"security": [{}]},
    responses={
        201: {"links": {"ReadModel": link("read_model", "model_id", "model_id")}},
        **responses(401, 403, 409, 422, 429, 503),
    },
)
async def submit(
    manifest: Manifest,
    credentials: BearerDep,
    request: Request,
    screening: ScreeningDep,
    writer: SubmissionsDep,
    settings: SettingsDep,
) -> SubmitPublic:
    """Screen an FSN weight manifest and store it as the participant's next model version.

    A new participant name is registered on the spot and its ``token`` is returned once; later
    versions of that participant need ``Authorization: Bearer <token>``. Rejected models are
    stored with their reasons and never enter an auction; a model whose deciding evidence lies
    within ``SRD_REVIEW_MARGIN`` of its bar is ``held`` for an inspector and enters none until
    admitted.
    """
    stored, verdict, status = await models.submit(
        screening,
        writer,
        manifest,
        bearer=None if credentials is None else credentials.credentials,
        address=request.client.host if request.client is not None else None,
        margin=settings.review_margin,
    )
    return SubmitPublic(
        model_id=stored.model_id,
        participant=stored.participant,
        version=stored.version,
        accepted=status == ModelStatus.ACCEPTED,
        status=status,
        reasons=[ReasonPublic(**reason.to_dict()) for reason in verdict.reasons],
        token=stored.token,
    )


@router.get("/models/{model_id}", operation_id="read_model", responses=responses(404, 422))
async def read_model(model_id: ModelIdPath, session: SessionDep) -> ModelPublic:
    """A stored model version: manifest, verdict (status), reasons and the screener's evidence;
    its audit log of reviews; for a version uploaded in a remote fine-tuning round, its parent
    version, auction and round; the auctions it entered."""
    row = await read_in_thread(models.read_model, session, model_id, auctions=MAX_LISTED_AUCTIONS)
    return model_public(row)


_VERDICTS: dict[str, VerdictName] = {
    ModelStatus.ACCEPTED: "accepted",
    ModelStatus.REFUSED: "rejected",
    ModelStatus.HELD: "held",
}
"""The verdict word of each status (``refused`` reads ``rejected``, as before statuses)."""


def verdict_name(status: str) -> VerdictName:
    """The verdict word of a status."""
    return _VERDICTS[status]


def review_entries(row: crud.StoredModel) -> list[ReviewPublic]:
    """A model's audit log."""
    return [ReviewPublic.model_validate(entry, from_attributes=True) for entry in row.reviews]


def model_public(row: crud.StoredModel) -> ModelPublic:
    """A stored version as ``GET /models/{id}`` shows it."""
    return ModelPublic(
        id=row.id,
        participant=row.participant,
        version=row.version,
        manifest=row.manifest,
        verdict=verdict_name(row.status),
        accepted=row.accepted,
        status=ModelStatus(row.status),
        reasons=_reasons(row),
        evidence=[EvidencePublic.model_validate(e) for e in row.evidence or []],
        reviews=review_entries(row),
        created_at=row.created_at,
        parent_id=row.parent_id,
        auction_id=row.auction_id,
        round=row.round,
        patron_id=row.patron_id,
        auctions=list(row.auctions),
    )


DESCRIPTION_PREVIEW = 160
"""Characters of a model's description that a list shows."""


def model_summary(row: crud.ModelSummary) -> ModelSummaryPublic:
    """A model version as the lists show it."""
    description = row.description or ""
    if len(description) > DESCRIPTION_PREVIEW:
        description = description[: DESCRIPTION_PREVIEW - 1] + "…"
    return ModelSummaryPublic(
        id=row.id,
        participant=row.participant,
        version=row.version,
        verdict=verdict_name(row.status),
        accepted=row.accepted,
        status=ModelStatus(row.status),
        description=description,
        n_reasons=len(row.reasons),
        rules=list(dict.fromkeys(reason["rule"] for reason in row.reasons)),
        created_at=row.created_at,
        inspected=row.inspected,
        appealed=row.appealed,
    )


@router.get("/models", operation_id="list_models", responses=responses(422))
async def list_models(
    session: SessionDep,
    participant: Annotated[
        Participant | None, Query(description="Only this participant's versions.")
    ] = None,
    accepted: Annotated[
        bool | None,
        Query(description="Only accepted (true) or only rejected (false: refused or held) models."),
        BeforeValidator(true_or_false),
    ] = None,
    status: Annotated[
        ModelStatus | None,
        Query(description="Only models with this status: accepted, refused or held."),
    ] = None,
    limit: PageLimit = DEFAULT_PAGE,
    cursor: PageCursor = None,
) -> ModelPage:
    """Model versions with their verdicts, newest first, a page at a time."""
    rows = await read_in_thread(
        crud.list_models,
        session,
        before=cursor,
        limit=limit + 1,
        participant=participant,
        accepted=accepted,
        status=status,
    )
    items, next_cursor = page_of(rows, limit)
    return ModelPage(items=[model_summary(row) for row in items], next_cursor=next_cursor)
