"""The patrons' votes in one committed iteration, explained (``GET
/auctions/{id}/iterations/{n}/votes`` and ``.../votes/{model_id}``)."""

from __future__ import annotations

import dataclasses

from sqlalchemy.orm import Session

from server.api.errors import api_error
from server.api.schemas.common import ReasonPublic
from server.api.schemas.votes import (
    IterationVotesPublic,
    MarketFineTuningPublic,
    PatronVotePublic,
    VotedWeightsPublic,
    VoteExplanationPublic,
)
from server.auctions.service import not_found
from server.store.crud.votes import bid_manifest, bidders, fine_tunings, iteration_votes


def explain_votes(session: Session, auction_id: int, iteration: int) -> IterationVotesPublic:
    """Every stored vote of a committed iteration; 404 naming the path part that names
    nothing: the auction, or an iteration not committed (or committed before explanations
    were kept)."""
    return _votes(session, auction_id, iteration, None)


def _votes(
    session: Session, auction_id: int, iteration: int, model_id: int | None
) -> IterationVotesPublic:
    """``explain_votes``, of the patron ``model_id`` only if given (the others' votes are
    not built: an iteration can hold thousands)."""
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
    who = bidders(session, auction_id=auction_id, iteration=iteration, only=model_id)
    return IterationVotesPublic(
        auction_id=auction_id,
        iteration=iteration,
        row=votes.explanations["row"],
        votes=[
            PatronVotePublic(
                model_id=vote["model_id"],
                **dataclasses.asdict(who[vote["model_id"]]),
                vote=vote["vote"],
                sensor=vote["sensor"],
                decision=vote["decision"],
                judgement=vote.get("judgement"),
                pfc=vote["pfc"],
            )
            for vote in votes.explanations["patrons"]
            if vote["model_id"] in who and model_id in (None, vote["model_id"])
        ],
    )


def explain_vote(
    session: Session, auction_id: int, iteration: int, model_id: int
) -> VoteExplanationPublic:
    """One patron's vote of ``explain_votes``; 404 also for a model that did not vote in it
    (not a patron, or gone: patrons leave when they buy or quit)."""
    every = _votes(session, auction_id, iteration, model_id)
    mine = every.votes
    if not mine:
        who = bidders(session, auction_id=auction_id, iteration=iteration)
        as_version = [m for m, bidder in who.items() if bidder.version_id == model_id]
        if model_id in who:  # a patron, gone by then
            why = ": it had left the auction (patrons leave when they buy or quit)"
        elif as_version:
            why = (
                f": it is the version patron {as_version[0]} bid with; the path names a patron "
                "by the id it entered with (the auction's model_ids)"
            )
        else:
            why = (
                " (the path names a patron by the id it entered with, the auction's "
                "model_ids; patrons leave when they buy or quit)"
            )
        raise api_error(
            404,
            f"model {model_id} did not vote in iteration {iteration} of auction {auction_id}" + why,
            loc=("path", "model_id"),
            kind="not_found",
        )
    return VoteExplanationPublic(
        **mine[0].model_dump(), auction_id=auction_id, iteration=iteration, row=every.row
    )


def voted_weights(
    session: Session, auction_id: int, iteration: int, model_id: int
) -> VotedWeightsPublic:
    """The weights behind ``explain_vote`` (the same 404s): the manifest of the version that
    bid, or the weights a server-mode auction had fine-tuned it to by then."""
    vote = explain_vote(session, auction_id, iteration, model_id)
    if not vote.weights_kept:
        raise api_error(
            404,
            f"the weights behind this vote were not kept: auction {auction_id} fine-tuned its "
            "patrons inside the market before this server kept fine-tuned weights",
            loc=("path", "model_id"),
            kind="not_found",
        )
    return VotedWeightsPublic(
        auction_id=auction_id,
        iteration=iteration,
        model_id=model_id,
        participant=vote.participant,
        version=vote.version,
        version_id=vote.version_id,
        fine_tuned_after=vote.fine_tuned_after,
        fine_tunings=[
            MarketFineTuningPublic(
                after=after, kept=kept, reasons=[ReasonPublic(**r) for r in reasons]
            )
            for after, kept, reasons in fine_tunings(
                session, auction_id=auction_id, model_id=model_id, iteration=iteration
            )
        ],
        manifest=bid_manifest(
            session,
            auction_id=auction_id,
            model_id=model_id,
            version_id=vote.version_id,
            fine_tuned_after=vote.fine_tuned_after,
        ),
    )
