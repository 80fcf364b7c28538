"""A patron's vote in one committed iteration, explained (``GET
/auctions/{id}/iterations/{n}/votes/{model_id}``)."""

from __future__ import annotations

from sqlalchemy.orm import Session

from server.api.errors import api_error
from server.api.schemas.votes import VoteExplanationPublic
from server.auctions.service import not_found
from server.store.crud.votes import bidding_version, iteration_votes


def explain_vote(
    session: Session, auction_id: int, iteration: int, model_id: int
) -> VoteExplanationPublic:
    """The stored explanation; 404 naming the path part that names nothing: the auction, an
    iteration not committed (or committed before explanations were kept), a model that did not
    vote in it (not a patron, or gone: patrons leave when they buy or quit)."""
    exists, votes = iteration_votes(session, auction_id=auction_id, iteration=iteration)
    if not exists:
        raise not_found(auction_id)
    if votes is None:
        raise api_error(
            404,
            f"auction {auction_id} has no committed iteration {iteration}",
            loc=("path", "iteration"),
            kind="not_found",
        )
    if votes.explanations is None:
        raise api_error(
            404,
            f"iteration {iteration} of auction {auction_id} was committed before votes were "
            "explained",
            loc=("path", "iteration"),
            kind="not_found",
        )
    mine = [p for p in votes.explanations["patrons"] if p["model_id"] == model_id]
    name = bidding_version(session, auction_id=auction_id, model_id=model_id, iteration=iteration)
    if not mine or name is None:
        raise api_error(
            404,
            f"model {model_id} did not vote in iteration {iteration} of auction {auction_id}",
            loc=("path", "model_id"),
            kind="not_found",
        )
    vote = mine[0]
    return VoteExplanationPublic(
        auction_id=auction_id,
        iteration=iteration,
        model_id=model_id,
        participant=name[0],
        version=name[1],
        vote=vote["vote"],
        row=votes.explanations["row"],
        sensor=vote["sensor"],
        decision=vote["decision"],
        pfc=vote["pfc"],
    )
