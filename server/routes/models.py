"""Models: ``POST /submit`` stores a screened manifest version, ``GET /models/{id}`` reads one."""

from __future__ import annotations

from fastapi import APIRouter, Request
from sqlalchemy.exc import IntegrityError

from agents.manifest import Manifest
from server import crud
from server.db import SessionDep
from server.errors import api_error, link, responses
from server.schemas import ModelIdPath, ModelPublic, ReasonPublic, SubmitPublic
from server.screening import ScreenerUnavailableError, ScreeningService
from server.security import BearerDep, token_matches

router = APIRouter(tags=["models"])


def _reasons(row: crud.StoredModel) -> list[ReasonPublic]:
    return [ReasonPublic.model_validate(reason) for reason in row.reasons]


@router.post(
    "/submit",
    status_code=201,
    operation_id="submit",
    responses={
        201: {"links": {"ReadModel": link("read_model", "model_id", "model_id")}},
        **responses(401, 403, 409, 422, 503),
    },
)
def submit(
    manifest: Manifest, session: SessionDep, credentials: BearerDep, request: Request
) -> SubmitPublic:
    """Screen an FSN weight manifest and store it as the participant's next model version.

    A new participant name is registered on the spot and its ``token`` is returned once; later
    versions of that participant need ``Authorization: Bearer <token>``. Rejected models are
    stored with their reasons and never enter an auction.
    """
    screening: ScreeningService = request.app.state.screening
    try:  # before any database work: no lock is held while screening
        verdict = screening.judge(manifest)
    except ScreenerUnavailableError as exc:
        raise api_error(503, str(exc), loc=("body",), kind="screener_unavailable") from exc
    participant = crud.get_participant(session, name=manifest.participant)
    token: str | None = None
    if participant is None:
        participant, token = crud.create_participant(session, name=manifest.participant)
    elif credentials is None:
        raise api_error(
            401,
            f"participant {manifest.participant!r} exists: send its token as "
            "'Authorization: Bearer <token>'",
            loc=("header", "Authorization"),
            kind="missing_token",
        )
    elif not token_matches(credentials.credentials, participant.token_hash):
        raise api_error(
            403,
            f"the bearer token is not the token of participant {manifest.participant!r}",
            loc=("header", "Authorization"),
            kind="bad_token",
        )
    try:
        model_id, version = crud.create_model_version(
            session,
            participant_id=participant.id,
            manifest=manifest.model_dump(mode="json"),
            verdict=verdict,
            first=token is not None,
        )
        session.commit()
    except IntegrityError as exc:  # a concurrent first submission took the name or version
        session.rollback()
        raise api_error(
            409,
            f"participant {manifest.participant!r} was written concurrently; retry",
            loc=("body", "participant"),
            kind="conflict",
        ) from exc
    return SubmitPublic(
        model_id=model_id,
        participant=participant.name,
        version=version,
        accepted=verdict.accepted,
        reasons=[ReasonPublic(**reason.to_dict()) for reason in verdict.reasons],
        token=token,
    )


@router.get("/models/{model_id}", operation_id="read_model", responses=responses(404, 422))
def read_model(model_id: ModelIdPath, session: SessionDep) -> ModelPublic:
    """A stored model version: manifest, verdict and reasons."""
    row = crud.get_model(session, model_id=model_id)
    if row is None:
        raise api_error(
            404, f"model {model_id} does not exist", loc=("path", "model_id"), kind="not_found"
        )
    return ModelPublic(
        id=row.id,
        participant=row.participant,
        version=row.version,
        manifest=row.manifest,
        verdict="accepted" if row.accepted else "rejected",
        accepted=row.accepted,
        reasons=_reasons(row),
        created_at=row.created_at,
    )
