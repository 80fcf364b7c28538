"""Bodies of participants and model versions: ``POST /submit``, ``GET /models/{id}``, the model
list, ``GET /participants/{name}``."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, Field, StringConstraints
from pydantic_core import PydanticCustomError

from agents.manifest import PlainLine, PlainText
from server.api.schemas.common import ReasonPublic, Schema, StrictInput
from server.store.status import AuctionStatus, ModelStatus

VerdictName = Literal["accepted", "rejected", "held"]
"""The verdict as the lists show it (``rejected``: the status ``refused``)."""


class EvidencePublic(Schema):
    """One bar the screener held the model to: ``measured`` must lie on ``side`` of ``bar``
    (in ``units``); ``detail`` explains the number (the decisive row's decisions with and
    without noise, the impact test's references). ``measured``/``bar`` null: no distance."""

    test: str
    measured: float | None
    bar: float | None
    units: str
    side: Literal["at least", "at most"]
    passed: bool
    detail: dict[str, Any]


class ReviewPublic(Schema):
    """An entry of a model's audit log: an inspector's decision (``admit``, ``refuse``) or its
    participant's ``appeal`` (``inspector`` is then the participant)."""

    decision: Literal["admit", "refuse", "appeal"]
    inspector: str
    note: str
    at: datetime


class SubmitPublic(Schema):
    """Answer to ``POST /submit``. ``token`` is set only on a participant's first submission."""

    model_id: int
    participant: str
    version: int
    accepted: bool
    """True only when ``status`` is accepted."""
    status: ModelStatus
    """accepted, refused, or held for an inspector (within ``SRD_REVIEW_MARGIN`` of a bar)."""
    reasons: list[ReasonPublic]
    token: str | None


class ModelPublic(Schema):
    """A stored model version: its manifest and the screener's verdict with reasons."""

    id: int
    participant: str
    version: int
    manifest: dict[str, Any]
    verdict: VerdictName
    accepted: bool
    status: ModelStatus
    reasons: list[ReasonPublic]
    evidence: list[EvidencePublic] = Field(default_factory=list)
    """The screener's bars (empty for versions stored before it was kept)."""
    reviews: list[ReviewPublic] = Field(default_factory=list)
    """Its audit log, oldest first."""
    created_at: datetime
    parent_id: int | None = None
    """The version this one was fine-tuned from (uploads of remote rounds only)."""
    auction_id: int | None = None
    """The auction whose fine-tuning round produced this version."""
    round: int | None = None
    """That round's number."""
    patron_id: int | None = None
    """The version its participant entered that auction with, for which this upload bids
    (uploads of remote rounds only; ``parent_id`` is the version it was fine-tuned from)."""
    auctions: list[int] = Field(default_factory=list)
    """Auctions this model entered as a patron, newest first (at most ``MAX_LISTED_AUCTIONS``)."""


MAX_LISTED_AUCTIONS = 100
"""Auctions listed on a model (newest first)."""


class ModelSummaryPublic(Schema):
    """A model version as a list shows it; ``rules`` are the screener rules that fired, once
    each, and ``description`` is cut to a preview (the whole text is on ``GET /models/{id}``)."""

    id: int
    participant: str
    version: int
    verdict: VerdictName
    accepted: bool
    status: ModelStatus
    description: str
    n_reasons: int
    rules: list[str]
    created_at: datetime
    inspected: bool = False
    """An inspector decided its status: admitted it (``accepted``) or refused it (``refused``),
    after the screener held it or its participant appealed."""
    appealed: bool = False
    """Its participant appealed the screener's refusal (once): it is held for an inspector
    until one decides, and ``inspected`` after that."""


class ModelPage(Schema):
    items: list[ModelSummaryPublic]
    next_cursor: int | None


EntryOutcome = Literal["bought", "quit", "joined", "bidding", "stayed", "stopped"]
"""How a patron left an auction, as a participant's page tells it (``EntryPublic``)."""


class EntryPublic(Schema):
    """An auction one of the participant's models entered as a patron, and how it left it."""

    auction_id: int
    auction_status: AuctionStatus
    model_id: int
    """The version that entered."""
    bidding_model_id: int
    """The version that bids now, or bid at the end: ``model_id`` unless remote fine-tuning
    rounds replaced it."""
    outcome: EntryOutcome
    """Bought a fish, quit, joined an auction that has not started (pending), bidding in a
    running one, stayed in without buying to a finished one's end, or still in when the
    auction stopped (cancelled or failed)."""
    price: float | None = None
    """What it paid (bought only)."""
    iteration: int | None = None
    """The iteration it bought or quit in."""


class ParticipantPublic(Schema):
    """A participant, its newest versions (all of them: ``GET /models?participant=``) and the
    newest auctions its models entered (a model's newest 100: ``GET /models/{id}``)."""

    name: str
    created_at: datetime
    n_versions: int
    versions: list[ModelSummaryPublic]
    auctions: list[EntryPublic] = Field(default_factory=list)
    """Newest first, at most a page of them."""


class TokenRotated(Schema):
    """A participant's new token (``POST /participants/{name}/token``): keep it; the old one is
    refused from now on."""

    participant: str
    token: str


def _not_blank(text: str) -> str:
    if not text.strip():
        raise PydanticCustomError("blank", "must name someone: it is blank")
    return text


Inspector = Annotated[
    str,
    StringConstraints(min_length=1, max_length=64),
    AfterValidator(_not_blank),
    PlainLine,
    Field(description="Who decides (a name, 1 to 64 characters, not blank, one line)."),
]
Note = Annotated[
    str,
    StringConstraints(max_length=2000),
    PlainText,
    Field(description="Why (at most 2000 characters)."),
]


class ReviewCreate(StrictInput):
    """``POST /models/{id}/review``: an inspector's decision on a held model."""

    decision: Literal["admit", "refuse"]
    inspector: Inspector
    note: Note = ""


class AppealCreate(StrictInput):
    """``POST /models/{id}/appeal``: why the participant asks for a person to look."""

    note: Annotated[str, StringConstraints(min_length=1, max_length=2000, pattern=r"\S"), PlainText]


class ReviewedPublic(Schema):
    """A model's verdict after a decision or an appeal, and its audit log."""

    model_id: int
    status: ModelStatus
    verdict: VerdictName
    accepted: bool
    reviews: list[ReviewPublic]


class LaterVersionPublic(Schema):
    """A later version of a held model's participant."""

    model_id: int
    version: int
    status: str


class HeldModelPublic(Schema):
    """A model held for an inspector: who, the screener's reasons and evidence; ``auction_id``
    and ``round`` for an upload of a remote round; ``appeal`` the participant's note when it
    came by appeal; ``later_versions`` the participant's versions since (newest first, at most
    10): deciding this one does not decide them."""

    id: int
    participant: str
    version: int
    reasons: list[ReasonPublic]
    evidence: list[EvidencePublic]
    created_at: datetime
    auction_id: int | None
    round: int | None
    appeal: str | None
    later_versions: list[LaterVersionPublic] = Field(default_factory=list)


class HeldPage(Schema):
    """``GET /reviews``: held models, oldest first; ``next_cursor`` pages on (ids above it)."""

    items: list[HeldModelPublic]
    next_cursor: int | None
    review_margin: float
    """``SRD_REVIEW_MARGIN`` (in price): a model whose deciding evidence misses its bar by no
    more than this is held rather than refused."""
