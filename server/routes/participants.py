"""Participants: ``GET /participants/{name}``, who submitted under a name and its versions."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path
from starlette.concurrency import run_in_threadpool

from agents.manifest import Participant
from server import crud
from server.db import SessionDep
from server.errors import api_error, responses
from server.pages import MAX_PAGE
from server.routes.models import model_summary
from server.schemas import ParticipantPublic

router = APIRouter(tags=["participants"])


@router.get("/participants/{name}", operation_id="read_participant", responses=responses(404, 422))
async def read_participant(
    name: Annotated[Participant, Path(description="A participant's name.")], session: SessionDep
) -> ParticipantPublic:
    """A participant with its newest versions (up to a page; ``GET /models?participant=`` pages
    through all of them) and how many it has."""
    view = await run_in_threadpool(crud.get_participant, session, name=name, limit=MAX_PAGE)
    if view is None:
        raise api_error(
            404, f"participant {name!r} does not exist", loc=("path", "name"), kind="not_found"
        )
    return ParticipantPublic(
        name=view.name,
        created_at=view.created_at,
        n_versions=view.n_versions,
        versions=[model_summary(row) for row in view.versions],
    )
