"""Auctions: create one over its patrons (operator), read one, cancel one (operator)."""

from __future__ import annotations

import logging
from datetime import timedelta

from sqlalchemy.orm import Session

from server.api.errors import RequestError, api_error, error_item
from server.api.schemas import MAX_PATRONS, AuctionCreate
from server.api.security import require_participant
from server.auctions.steps import base_price
from server.store import crud
from server.store.status import AuctionStatus, ModelStatus
from server.store.tables import utcnow
from server.work.runner import BackgroundRunner
from sim.market import fish_on_sale

LIVE_RETRY_AFTER_S = 30
"""``Retry-After`` of an auction refused while ``max_live_auctions`` are pending or running."""

log = logging.getLogger("srd.auctions")


def patron_ids(session: Session, model_ids: list[int] | None) -> list[int]:
    """The ordered patron list: the given ids (each must exist, 404, be accepted, 409: a
    refused or held one is named, and name a participant no other id names, 422), or by
    default the newest accepted version of every participant (a held version is passed over;
    409 while there is none)."""
    if model_ids is None:
        ids = [row.id for row in crud.latest_accepted_models(session)]
        if not ids:
            raise api_error(
                409,
                "no accepted model exists yet: submit models first",
                loc=("body", "model_ids"),
                kind="no_patrons",
            )
        if len(ids) > MAX_PATRONS:
            raise api_error(
                409,
                f"{len(ids)} participants have an accepted model, and an auction takes at most "
                f"{MAX_PATRONS} patrons: name them in model_ids",
                loc=("body", "model_ids"),
                kind="too_many_patrons",
            )
        return ids
    found = crud.get_models(session, model_ids=model_ids)
    missing = [
        error_item(
            f"model {model_id} does not exist", loc=("body", "model_ids", i), kind="not_found"
        )
        for i, model_id in enumerate(model_ids)
        if model_id not in found
    ]
    if missing:
        raise RequestError(404, missing)
    rejected = [
        error_item(
            f"model {model_id} is held for an inspector's review and cannot enter an auction "
            "until admitted"
            if found[model_id].status == ModelStatus.HELD
            else f"model {model_id} was rejected (by the screener, or an inspector after it) "
            "and cannot enter an auction",
            loc=("body", "model_ids", i),
            kind="held" if found[model_id].status == ModelStatus.HELD else "rejected",
        )
        for i, model_id in enumerate(model_ids)
        if not found[model_id].accepted
    ]
    if rejected:
        raise RequestError(409, rejected)
    first: dict[int, int] = {}  # participant → the model naming it first
    twice = []
    for i, model_id in enumerate(model_ids):
        participant = found[model_id].participant_id
        if participant in first and first[participant] != model_id:
            twice.append(
                error_item(
                    f"model {model_id} is another version of the participant of model "
                    f"{first[participant]}: a participant takes part once (one version, one vote)",
                    loc=("body", "model_ids", i),
                    kind="same_participant",
                )
            )
        first.setdefault(participant, model_id)
    if twice:
        raise RequestError(422, twice)
    return list(model_ids)


def _fish_count(body: AuctionCreate, n_patrons: int) -> int:
    """The market's rule (``fish_on_sale``): n_fish, or int(rarity × patrons); exactly one."""
    try:
        return fish_on_sale(n_patrons, n_fish=body.n_fish, rarity=body.rarity)
    except ValueError as exc:
        loc = ("body", "n_fish") if body.n_fish is not None else ("body", "rarity")
        raise api_error(422, str(exc), loc=loc, kind="n_fish_xor_rarity") from exc


def _remote_fine_tuning(body: AuctionCreate) -> bool:
    """Whether the participants fine-tune (remote); refuses settings that contradict it, and
    fine-tuning rounds that change nothing (given without fine-tuning, or 0 with it)."""
    remote = body.fine_tune_mode == "remote"
    if remote and "fine_tune" in body.model_fields_set and not body.fine_tune:
        raise api_error(
            422,
            "a remote auction fine-tunes: leave fine_tune out or set it true",
            loc=("body", "fine_tune"),
            kind="remote_fine_tune",
        )
    if not remote and "round_deadline_s" in body.model_fields_set:
        raise api_error(
            422,
            'round_deadline_s applies to fine_tune_mode "remote" only',
            loc=("body", "round_deadline_s"),
            kind="remote_only",
        )
    if not (remote or body.fine_tune) and "fine_tune_rounds" in body.model_fields_set:
        raise api_error(
            422,
            "without fine-tuning nothing is fine-tuned: fine_tune_rounds changes nothing (set "
            'fine_tune true, or fine_tune_mode "remote")',
            loc=("body", "fine_tune_rounds"),
            kind="changes_nothing",
        )
    if (remote or body.fine_tune) and body.fine_tune_rounds == 0:
        raise api_error(
            422,
            "0 rounds fine-tune nothing: give at least 1, or leave fine-tuning off",
            loc=("body", "fine_tune_rounds"),
            kind="changes_nothing",
        )
    return remote


def create_auction(
    session: Session, runner: BackgroundRunner, body: AuctionCreate, *, max_live: int
) -> int:
    """Store a pending auction and hand it to the runner; its id. The either-or of the supply
    is checked first, then the fine-tuning mode, then the patrons, then the fish count, then
    that fewer than ``max_live`` auctions are pending or running (503 otherwise)."""
    _fish_count(body, 0)
    remote = _remote_fine_tuning(body)
    enrolling = body.enrollment_s > 0
    # An enrolling auction starts with the models named (none by default); its participants
    # add theirs until its enrollment ends, and then a rarity's fish are counted.
    if enrolling and body.model_ids is None:
        patrons: list[int] = []
    else:
        patrons = patron_ids(session, body.model_ids)
    n_fish = _fish_count(body, len(patrons))
    if n_fish < 1 and not (enrolling and body.rarity is not None):
        raise api_error(
            409,
            f"rarity {body.rarity} × {len(patrons)} patrons puts no fish on sale",
            loc=("body", "rarity"),
            kind="no_fish",
        )
    crud.lock_subject(session, "live-auctions")  # concurrent creations count one another
    live = crud.count_live(session)
    if live >= max_live:
        raise api_error(
            503,
            f"{live} auctions are pending or running, the most this server holds "
            "(SRD_MAX_LIVE_AUCTIONS); retry once some have ended",
            loc=("server",),
            kind="too_many_auctions",
            headers={"Retry-After": str(LIVE_RETRY_AFTER_S)},
        )
    auction = crud.create_auction(
        session,
        model_ids=patrons,
        n_fish=n_fish,
        rarity=body.rarity,
        max_iterations=body.max_iterations,
        fine_tune=body.fine_tune or remote,
        seed=body.seed,
        opening_price=base_price(),
        fine_tune_mode=body.fine_tune_mode,
        fine_tune_rounds=body.fine_tune_rounds,
        round_deadline_s=body.round_deadline_s,
        buy_fraction=body.buy_fraction,
        n_rows=body.rows,
        enroll_until=utcnow() + timedelta(seconds=body.enrollment_s) if enrolling else None,
    )
    session.commit()
    runner.submit(auction.id)
    return auction.id


def join_auction(
    session: Session, auction_id: int, model_id: int, token: str
) -> tuple[crud.Enrollment, int, bool]:
    """Add a participant's accepted model to an enrolling auction's patrons (its token: 401,
    403); the auction's enrollment and the patron's position. Refused (409) once the
    enrollment is over or if the auction never enrolled, for a model that is not accepted,
    for a second version of a participant already in, past ``MAX_PATRONS``. The same model
    again is answered as the first time; the last of the three says whether it joined now."""
    owner = crud.model_owner(session, model_id=model_id)
    if owner is None:
        raise api_error(
            404, f"model {model_id} does not exist", loc=("body", "model_id"), kind="not_found"
        )
    require_participant(token, owner.token_hash, owner.participant)
    enrollment = crud.lock_enrollment(session, auction_id=auction_id)
    if enrollment is None:
        raise not_found(auction_id)
    joined = enrollment.patrons.get(owner.participant_id)
    if joined is not None and joined[0] == model_id:  # a repeat
        return enrollment, joined[1], False
    open_until = enrollment.enroll_until
    if enrollment.status != AuctionStatus.PENDING or open_until is None or utcnow() >= open_until:
        raise api_error(
            409,
            f"auction {auction_id} ({enrollment.status}) takes no patrons now: models join "
            "only while an auction created with enrollment_s enrolls (pending, until its "
            "enroll_until)",
            loc=("path", "auction_id"),
            kind="not_enrolling",
        )
    if owner.status != ModelStatus.ACCEPTED:
        raise api_error(
            409,
            f"model {model_id} is {owner.status}: only an accepted model enters an auction",
            loc=("body", "model_id"),
            kind=str(owner.status),
        )
    if joined is not None:
        raise api_error(
            409,
            f"the participant of model {model_id} takes part already, with model "
            f"{joined[0]}: one version, one vote",
            loc=("body", "model_id"),
            kind="same_participant",
        )
    if len(enrollment.patrons) >= MAX_PATRONS:
        raise api_error(
            409,
            f"auction {auction_id} has {MAX_PATRONS} patrons, the most an auction takes",
            loc=("path", "auction_id"),
            kind="too_many_patrons",
        )
    position = len(enrollment.patrons)
    crud.add_patron(session, auction_id=auction_id, model_id=model_id, position=position)
    session.commit()
    enrollment.patrons[owner.participant_id] = (model_id, position)
    return enrollment, position, True


def not_found(auction_id: int) -> RequestError:
    """The 404 of an auction id that names none."""
    return api_error(
        404, f"auction {auction_id} does not exist", loc=("path", "auction_id"), kind="not_found"
    )


def read_auction(session: Session, auction_id: int) -> crud.AuctionView:
    """An auction with its rounds, buyers and quitters (404 if there is none)."""
    view = crud.get_auction(session, auction_id=auction_id)
    if view is None:
        raise not_found(auction_id)
    return view


def require_auction(session: Session, auction_id: int) -> crud.AuctionState:
    """Where an auction stands (404 if there is none)."""
    state = crud.auction_state(session, auction_id=auction_id)
    if state is None:
        raise not_found(auction_id)
    return state


def cancel_auction(session: Session, runner: BackgroundRunner, auction_id: int) -> crud.AuctionView:
    """Cancel a pending or running auction (404 if there is none, 409 once it has ended), its
    open fine-tuning round closed in the same transaction, and stop its worker; the auction as
    it now stands."""
    require_auction(session, auction_id)
    if not crud.cancel_auction(session, auction_id=auction_id):
        session.rollback()
        ended = require_auction(session, auction_id)
        raise api_error(
            409,
            f"auction {auction_id} already {ended.status}; only pending or running auctions "
            "can be cancelled",
            loc=("path", "auction_id"),
            kind="not_cancellable",
        )
    session.commit()
    log.info("auction %d cancelled", auction_id)
    # A worker that is not stopped in time (another replica's, until its lease renewal) still
    # commits nothing: its writes require the auction running.
    runner.cancel(auction_id)
    return read_auction(session, auction_id)
