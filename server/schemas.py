"""Request and response bodies of the HTTP API (separate from the table classes)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal, get_args

from fastapi import Path
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from sim.registry import KINDS

AuctionStatus = Literal["pending", "running", "finished", "failed"]
JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
JobKind = Literal["fish", "lavaland", "cheetah", "auction-study", "comparison"]
assert set(get_args(JobKind)) == set(KINDS), "JobKind must list exactly the registry's kinds"

MAX_PATRONS = 10_000
MAX_SEED = 2**31 - 1  # fits a 32-bit INTEGER column on every backend
MAX_ROW_ID = 2**31 - 1  # ids are 32-bit INTEGER primary keys on every backend


def _decimal(value: Any) -> Any:
    """A path id is written in ASCII digits only: ``1.0``, ``1 `` or ``+1`` name no row."""
    if isinstance(value, str) and not (value.isascii() and value.isdigit()):
        raise ValueError("must be a positive integer written in digits")
    return value


RowId = Annotated[int, Field(ge=1, le=MAX_ROW_ID)]
ModelIdPath = Annotated[
    int, BeforeValidator(_decimal), Path(ge=1, le=MAX_ROW_ID, description="A model id.")
]
AuctionIdPath = Annotated[
    int, BeforeValidator(_decimal), Path(ge=1, le=MAX_ROW_ID, description="An auction id.")
]
JobIdPath = Annotated[
    int, BeforeValidator(_decimal), Path(ge=1, le=MAX_ROW_ID, description="A job id.")
]


class _Input(BaseModel):
    """A request body: unknown keys refused; numbers, booleans and integers typed strictly
    (``"3"``, ``true`` or ``3.0`` are not the integer 3)."""

    model_config = ConfigDict(extra="forbid", strict=True)


class HealthPublic(BaseModel):
    status: Literal["ok"]


class ReasonPublic(BaseModel):
    """A screener finding."""

    rule: str
    neuron: str
    message: str


class SubmitPublic(BaseModel):
    """Answer to ``POST /submit``. ``token`` is set only on a participant's first submission."""

    model_id: int
    participant: str
    version: int
    accepted: bool
    reasons: list[ReasonPublic]
    token: str | None


class ModelPublic(BaseModel):
    """A stored model version: its manifest and the screener's verdict with reasons."""

    id: int
    participant: str
    version: int
    manifest: dict[str, Any]
    verdict: Literal["accepted", "rejected"]
    accepted: bool
    reasons: list[ReasonPublic]
    created_at: datetime


class AuctionCreate(_Input):
    """Start an auction: exactly one of ``n_fish`` or ``rarity`` (fish = int(rarity × patrons))."""

    n_fish: Annotated[int, Field(ge=1, le=100_000)] | None = None
    rarity: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] | None = None
    max_iterations: Annotated[int, Field(ge=1, le=1000)] = 64
    fine_tune: bool = False
    model_ids: Annotated[list[RowId], Field(min_length=1, max_length=MAX_PATRONS)] | None = None
    seed: Annotated[int, Field(ge=0, le=MAX_SEED)] = 0


class AuctionCreated(BaseModel):
    auction_id: int


class Votes(BaseModel):
    """Row-0 decisions of the patrons still in the auction."""

    buy: int
    hold: int
    quit: int


class IterationPublic(BaseModel):
    """One auction round: price asked and fish left at its start, the votes, what followed."""

    iteration: int
    price: float
    n_available: int
    votes: Votes
    row_votes: Votes
    next_price: float
    n_available_after: int


class BuyerPublic(BaseModel):
    model_id: int
    price: float
    iteration: int


class AuctionPublic(BaseModel):
    """An auction as it stands; ``history`` grows by one committed row per round."""

    id: int
    status: AuctionStatus
    iteration: int
    price: float
    n_available: int
    n_initial: int
    history: list[IterationPublic]
    buyers: list[BuyerPublic]
    quitters: list[int]
    stop_reason: str | None
    n_patrons: int
    model_ids: list[int]
    revenue: float
    rarity: float | None
    max_iterations: int
    fine_tune: bool
    seed: int
    error: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobCreate(_Input):
    """Start an experiment; ``params`` are the CLI options of that kind (dashes or underscores)."""

    kind: JobKind
    params: dict[str, Any] = Field(default_factory=dict)


class JobCreated(BaseModel):
    job_id: int
    status: JobStatus


class JobPublic(BaseModel):
    """A job; ``result`` is the CLI's ``--json`` object once it succeeded."""

    id: int
    kind: str
    status: JobStatus
    progress: Annotated[float, Field(ge=0, le=1)]
    message: str
    params: dict[str, Any]
    result: dict[str, Any] | None
    error: str | None
    artifacts: list[str]
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


# Lists (``GET /auctions``, ``/models``, ``/jobs``): one page, newest first, and the cursor of
# the next page (null on the last one).


class AuctionSummaryPublic(BaseModel):
    """An auction as a list shows it."""

    id: int
    status: AuctionStatus
    n_initial: int
    n_available: int
    n_sold: int
    n_patrons: int
    iteration: int
    price: float
    revenue: float
    stop_reason: str | None
    rarity: float | None
    fine_tune: bool
    created_at: datetime
    finished_at: datetime | None


class AuctionPage(BaseModel):
    items: list[AuctionSummaryPublic]
    next_cursor: str | None


class ModelSummaryPublic(BaseModel):
    """A model version as a list shows it; ``rules`` are the screener rules that fired, once
    each, and ``description`` is cut to a preview (the whole text is on ``GET /models/{id}``)."""

    id: int
    participant: str
    version: int
    verdict: Literal["accepted", "rejected"]
    accepted: bool
    description: str
    n_reasons: int
    rules: list[str]
    created_at: datetime


class ModelPage(BaseModel):
    items: list[ModelSummaryPublic]
    next_cursor: str | None


class JobSummaryPublic(BaseModel):
    """A job as a list shows it (its result and error are on ``GET /jobs/{id}``)."""

    id: int
    kind: str
    status: JobStatus
    progress: Annotated[float, Field(ge=0, le=1)]
    message: str
    params: dict[str, Any]
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobPage(BaseModel):
    items: list[JobSummaryPublic]
    next_cursor: str | None


class ParticipantPublic(BaseModel):
    """A participant and its newest versions (all of them: ``GET /models?participant=``)."""

    name: str
    created_at: datetime
    n_versions: int
    versions: list[ModelSummaryPublic]


# Event stream payloads (the ``data`` of each Server-Sent Event, as JSON).


class PatronPublic(BaseModel):
    """A patron: its model id and the participant and version behind it."""

    model_id: int
    participant: str
    version: int


class RoundPurchasePublic(PatronPublic):
    price: float


class IterationEvent(IterationPublic):
    """``event: iteration`` (``id`` = ``iteration``): one committed round, its purchases and
    quits."""

    purchases: list[RoundPurchasePublic]
    quits: list[PatronPublic]


class AuctionEndEvent(BaseModel):
    """``event: end``: the auction is over (the stream closes after it)."""

    status: AuctionStatus
    iterations: int
    price: float
    n_available: int
    n_initial: int
    n_sold: int
    stop_reason: str | None
    error: str | None
    finished_at: datetime | None


class JobProgressEvent(BaseModel):
    """``event: progress``: the job's status, progress and message changed."""

    status: JobStatus
    progress: Annotated[float, Field(ge=0, le=1)]
    message: str
