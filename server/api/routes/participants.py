"""Participants: ``GET /participants/{name}``, who submitted under a name and its versions."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path

from agents.manifest import Participant
from server.api.deps import SessionDep, read_in_thread
from server.api.errors import responses
from server.api.pages import MAX_PAGE
from server.api.routes.models import model_summary
from server.api.schemas import ParticipantPublic
from server.submissions import service as models

router = APIRouter(tags=["participants"])


@router.get("/participants/{name}", operation_id="read_participant", responses=responses(404, 422))
async def read_participant(
    name: Annotated[Participant, Path(description="A participant's name.")], session: SessionDep
) -> ParticipantPublic:
    """A participant with its newest versions (up to a page; ``GET /models?participant=`` pages
    through all of them) and how many it has."""
    view = await read_in_thread(models.read_participant, session, name, limit=MAX_PAGE)
    return ParticipantPublic(
        name=view.name,
        created_at=view.created_at,
        n_versions=view.n_versions,
        versions=[model_summary(row) for row in view.versions],
    )
