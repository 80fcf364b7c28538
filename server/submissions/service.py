"""Models and participants: submit a manifest (screened, then stored as the participant's next
version), read a version, read a participant."""

from __future__ import annotations

from sqlalchemy.orm import Session

from agents.manifest import Manifest, name_problem
from screener import Verdict, review, with_hold_reasons
from server.api.connections import client_address
from server.api.errors import RequestError, api_error
from server.api.security import hash_token, new_token, require_participant, token_matches
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


def rotate_token(session: Session, name: str, *, token: str, admin_hash: str) -> tuple[str, str]:
    """A new token for the participant named ``name`` (its exact name, 404 otherwise), given
    its current token or the operator's (403 with any other); the participant's name and the
    new token, whose hash replaces the old one's (the old token is refused from the commit
    on)."""
    row = crud.participant_by_name(session, name=name)  # locked until the commit
    if row is None or row.name != name:
        raise api_error(
            404, f"participant {name!r} does not exist", loc=("path", "name"), kind="not_found"
        )
    if not token_matches(token, admin_hash):
        require_participant(token, row.token_hash, row.name)
    fresh = new_token(crud.PARTICIPANT_TOKEN_PREFIX)
    crud.set_token_hash(session, participant_id=row.id, token_hash=hash_token(fresh))
    session.commit()
    return row.name, fresh


def read_participant(session: Session, name: str, *, limit: int) -> crud.ParticipantView:
    """A participant with its newest ``limit`` versions (404 if the name is not registered)."""
    view = crud.get_participant(session, name=name, limit=limit)
    if view is None:
        raise api_error(
            404, f"participant {name!r} does not exist", loc=("path", "name"), kind="not_found"
        )
    return view
