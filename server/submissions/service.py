"""Models and participants: submit a manifest (screened, then stored as the participant's next
version), read a version, read a participant."""

from __future__ import annotations

from sqlalchemy.orm import Session

from agents.manifest import Manifest, name_problem
from screener import Verdict, review, with_hold_reasons
from server.api.connections import client_address
from server.api.errors import RequestError, api_error
from server.screening.pool import ScreenerUnavailableError, ScreeningService
from server.store import crud
from server.store.status import ModelStatus
from server.submissions.writer import Refused, Stored, SubmissionWriter

SCREENER_RETRY_AFTER_S = 2
"""``Retry-After`` of a submission the screener could not judge: its process is restarted in
about a second."""


def _refusal(refused: Refused) -> RequestError:
    headers = None
    if refused.retry_after_s is not None:
        headers = {"Retry-After": str(refused.retry_after_s)}
    return api_error(
        refused.status, refused.msg, loc=refused.loc, kind=refused.kind, headers=headers
    )


async def submit(
    screening: ScreeningService,
    writer: SubmissionWriter,
    manifest: Manifest,
    *,
    bearer: str | None,
    address: str | None,
    margin: float,
) -> tuple[Stored, Verdict, ModelStatus]:
    """Check the token and the quotas (nothing spent on a refused request), screen the
    manifest (no database lock held meanwhile), store it with its verdict, held for an
    inspector within ``margin`` of a bar (``screener.review``); the stored version, the
    verdict and its status."""
    problem = name_problem(manifest.participant)
    if problem is not None:
        raise api_error(
            422,
            problem,
            loc=("body", "participant"),
            kind="bad_name",
        )
    refused = await writer.precheck(
        participant=manifest.participant, bearer=bearer, address=address
    )
    if refused is not None:
        raise _refusal(refused)
    try:
        client = None if address is None else client_address(address)
        verdict = await screening.verdict(manifest, client=client)
    except ScreenerUnavailableError as exc:
        raise api_error(
            503,
            str(exc),
            loc=("server",),
            kind="screener_unavailable",
            headers={"Retry-After": str(SCREENER_RETRY_AFTER_S)},
        ) from exc
    status = ModelStatus(review(verdict, margin))
    verdict = with_hold_reasons(verdict, margin)
    outcome = await writer.store(
        participant=manifest.participant,
        manifest=manifest.model_dump(mode="json"),
        verdict=verdict,
        status=status,
        bearer=bearer,
        address=address,
    )
    if isinstance(outcome, Refused):
        raise _refusal(outcome)
    return outcome, verdict, status


def read_model(session: Session, model_id: int, *, auctions: int) -> crud.StoredModel:
    """A stored version with the first ``auctions`` auctions it entered (404 if none)."""
    row = crud.get_model_view(session, model_id=model_id, auctions=auctions)
    if row is None:
        raise api_error(
            404, f"model {model_id} does not exist", loc=("path", "model_id"), kind="not_found"
        )
    return row


def read_participant(session: Session, name: str, *, limit: int) -> crud.ParticipantView:
    """A participant with its newest ``limit`` versions (404 if the name is not registered)."""
    view = crud.get_participant(session, name=name, limit=limit)
    if view is None:
        raise api_error(
            404, f"participant {name!r} does not exist", loc=("path", "name"), kind="not_found"
        )
    return view
