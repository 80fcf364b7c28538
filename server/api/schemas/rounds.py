"""Bodies of remote fine-tuning rounds: a round and its answers as an auction shows them,
``GET /auctions/{id}/rounds/current``, the answer to an upload."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from server.api.schemas.common import ReasonPublic, Schema
from server.store.status import AnswerOutcome, AuctionStatus, RoundStatus

FineTuneModeName = Literal["server", "remote"]


class RoundAnswerPublic(Schema):
    """A patron's outcome in a fine-tuning round: accepted (its upload bids from the next
    iteration), refused (re-screening failed; its previous version bids on), held (within the
    review margin of a bar: its previous version bids on), late (after the
    deadline), missing (no upload); ``version`` bids after the round."""

    model_id: int
    """The patron, as in the auction's ``model_ids``."""
    outcome: AnswerOutcome
    version: int
    version_id: int
    """The model id of that version."""
    uploaded_id: int | None
    """The version stored from the upload (accepted or refused), if one was."""
    bytes_in: int
    bytes_out: int


class FineTuneRoundPublic(Schema):
    """A remote fine-tuning round: when, and who answered how; traffic in bytes of bodies
    (``bytes_published``: the round's rows as JSON once to every asked patron, what publishing
    it costs, not a count of the answers sent; uploads and their answers per patron, as
    received and sent; ``bytes_total``: all of them)."""

    round: int
    iteration: int
    status: RoundStatus
    opened_at: datetime
    deadline: datetime
    closed_at: datetime | None
    bytes_published: int
    bytes_total: int
    answers: list[RoundAnswerPublic]


class RoundPublic(Schema):
    """``GET /auctions/{id}/rounds/current``: the newest fine-tuning round. ``rows`` (R × 8: p,
    l, w, g, st1, st2, st3, f) and ``asked`` (model ids) are given while it is open; a patron
    fine-tunes on the rows with the seeds, and its own model makes the D_ic noisy copies."""

    auction_id: int
    auction_status: AuctionStatus
    fine_tune_mode: FineTuneModeName
    fine_tune_rounds: int | None
    """As ``GET /auctions/{id}`` gives it: None for an auction that does not fine-tune."""
    round: int | None
    iteration: int | None
    status: Literal["open", "closed", "none"]
    deadline: datetime | None
    seconds_left: float
    rows: list[list[float]] | None
    fine_tune_seed: int | None
    augmentation_seed: int | None
    asked: list[int]


class UploadPublic(Schema):
    """The answer to an upload: accepted (a new version, ``model_id``, bids from the next
    iteration; the same weights as now keep the version), refused with the screener's reasons,
    or held for an inspector (``version`` is the one that keeps bidding; ``uploaded_id`` the
    refused or held one)."""

    round: int
    outcome: Literal["accepted", "refused", "held"]
    accepted: bool
    reasons: list[ReasonPublic]
    version: int
    model_id: int
    parent_id: int
    uploaded_id: int | None
