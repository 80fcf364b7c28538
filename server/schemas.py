"""Request and response bodies of the HTTP API (separate from the table classes)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal, get_args

from fastapi import Path
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    GetJsonSchemaHandler,
    JsonValue,
    field_validator,
)
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import CoreSchema

from server.config import JobBackendName
from server.status import AnswerOutcome, AuctionStatus, JobStatus, RoundStatus
from sim.experiment import config_schema
from sim.market import MarketConfig
from sim.registry import KINDS

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
    int, Path(ge=1, le=MAX_ROW_ID, description="A model id."), BeforeValidator(_decimal)
]
AuctionIdPath = Annotated[
    int, Path(ge=1, le=MAX_ROW_ID, description="An auction id."), BeforeValidator(_decimal)
]
JobIdPath = Annotated[
    int, Path(ge=1, le=MAX_ROW_ID, description="A job id."), BeforeValidator(_decimal)
]


class _Input(BaseModel):
    """A request body: unknown keys refused; numbers, booleans and integers typed strictly
    (``"3"``, ``true`` or ``3.0`` are not the integer 3)."""

    model_config = ConfigDict(extra="forbid", strict=True)


class HealthPublic(BaseModel):
    status: Literal["ok"]
    job_backend: JobBackendName
    """Where job units are computed (``SRD_JOB_BACKEND``)."""
    cpus: float
    """The CPUs that backend computes on: this machine's, or the Ray cluster's live nodes'."""


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
    parent_id: int | None = None
    """The version this one was fine-tuned from (uploads of remote rounds only)."""
    auction_id: int | None = None
    """The auction whose fine-tuning round produced this version."""
    round: int | None = None
    """That round's number."""
    auctions: list[int] = Field(default_factory=list)
    """Auctions this model entered as a patron, newest first (at most ``MAX_LISTED_AUCTIONS``)."""


MAX_LISTED_AUCTIONS = 100
"""Auctions listed on a model (newest first)."""
ROUND_DEADLINE_S = (0.5, 300.0)
"""Bounds of a remote auction's ``round_deadline_s``: how long a round waits at most."""
MAX_FINE_TUNE_ROUNDS = 64
"""Fine-tuning rounds of an auction, at most (each may wait a whole deadline)."""
FineTuneModeName = Literal["server", "remote"]


_REMOTE: dict[str, JsonValue] = {
    "properties": {"fine_tune_mode": {"const": "remote"}},
    "required": ["fine_tune_mode"],
}
"""JSON Schema: a remote auction."""


def _absent(schema: dict[str, Any]) -> None:
    """The schema of an optional field that may be left out but is never ``null``: its value's
    schema alone (the validator refuses an explicit null)."""
    value = schema.pop("anyOf")[0]
    schema.pop("default", None)
    schema.update(value)


def _unique_ids(schema: dict[str, Any]) -> None:
    """``model_ids``: left out or a list of distinct ids."""
    _absent(schema)
    schema["uniqueItems"] = True


class AuctionCreate(_Input):
    """Start an auction: exactly one of ``n_fish`` or ``rarity`` (fish = int(rarity × patrons)).

    ``fine_tune_mode`` "remote": the participants fine-tune their own patrons over HTTP, in
    rounds after each of the first ``fine_tune_rounds`` iterations, each round waiting at most
    ``round_deadline_s``. A remote auction fine-tunes (``fine_tune`` may be left out; false is
    refused); ``round_deadline_s`` belongs to remote auctions only."""

    model_config = ConfigDict(
        json_schema_extra={
            "oneOf": [{"required": ["n_fish"]}, {"required": ["rarity"]}],
            "allOf": [
                {  # a remote auction fine-tunes: fine_tune, if given, is true
                    "if": _REMOTE,
                    "then": {"properties": {"fine_tune": {"const": True}}},
                },
                {  # a round deadline belongs to remote auctions
                    "if": {"not": _REMOTE},
                    "then": {"not": {"required": ["round_deadline_s"]}},
                },
            ],
        }
    )

    n_fish: Annotated[int, Field(ge=1, le=100_000)] | None = Field(None, json_schema_extra=_absent)
    rarity: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] | None = Field(
        None, json_schema_extra=_absent
    )
    max_iterations: Annotated[int, Field(ge=1, le=1000)] = MarketConfig.max_iterations
    fine_tune: bool = False
    model_ids: Annotated[list[RowId], Field(min_length=1, max_length=MAX_PATRONS)] | None = Field(
        None, json_schema_extra=_unique_ids
    )
    seed: Annotated[int, Field(ge=0, le=MAX_SEED)] = 0
    fine_tune_mode: FineTuneModeName = "server"
    fine_tune_rounds: Annotated[int, Field(ge=0, le=MAX_FINE_TUNE_ROUNDS)] = (
        MarketConfig.fine_tune_rounds
    )
    round_deadline_s: Annotated[
        float, Field(ge=ROUND_DEADLINE_S[0], le=ROUND_DEADLINE_S[1], allow_inf_nan=False)
    ] = 10.0

    @field_validator("model_ids")
    @classmethod
    def _distinct(cls, ids: list[int] | None) -> list[int] | None:
        """A patron takes part once."""
        if ids is not None and len(set(ids)) != len(ids):
            twice = sorted({i for i in ids if ids.count(i) > 1})
            raise ValueError(f"model ids listed more than once: {twice}")
        return ids

    @field_validator("n_fish", "rarity", "model_ids", mode="before")
    @classmethod
    def _absent_not_null(cls, value: Any) -> Any:
        """An option left out is absent; ``null`` is not one of its values."""
        if value is None:
            raise ValueError("must not be null: leave it out instead")
        return value


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
    fine_tune_mode: FineTuneModeName = "server"
    fine_tune_rounds: int = 4
    round_deadline_s: float = 10.0
    fine_tuning: list[FineTuneRoundPublic] = Field(default_factory=list)
    """Remote auctions: every fine-tuning round with each asked patron's outcome."""
    current_model_ids: list[int] = Field(default_factory=list)
    """Remote auctions: the version each patron bids with now, aligned with ``model_ids``."""


class RoundAnswerPublic(BaseModel):
    """A patron's outcome in a fine-tuning round: accepted (its upload bids from the next
    iteration), refused (re-screening failed; its previous version bids on), late (after the
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


class FineTuneRoundPublic(BaseModel):
    """A remote fine-tuning round: when, and who answered how; traffic in bytes of bodies
    (``bytes_published``: the round answers of ``GET .../rounds/current``; uploads and their
    answers per patron; ``bytes_total``: all of them)."""

    round: int
    iteration: int
    status: RoundStatus
    opened_at: datetime
    deadline: datetime
    closed_at: datetime | None
    bytes_published: int
    bytes_total: int
    answers: list[RoundAnswerPublic]


class RoundPublic(BaseModel):
    """``GET /auctions/{id}/rounds/current``: the newest fine-tuning round. ``rows`` (R × 8: p,
    l, w, g, st1, st2, st3, f) and ``asked`` (model ids) are given while it is open; a patron
    fine-tunes on the rows with the seeds, and its own model makes the D_ic noisy copies."""

    auction_id: int
    auction_status: AuctionStatus
    fine_tune_mode: FineTuneModeName
    fine_tune_rounds: int
    round: int | None
    iteration: int | None
    status: Literal["open", "closed", "none"]
    deadline: datetime | None
    seconds_left: float
    rows: list[list[float]] | None
    fine_tune_seed: int | None
    augmentation_seed: int | None
    asked: list[int]


class UploadPublic(BaseModel):
    """The answer to an upload: accepted (a new version, ``model_id``, bids from the next
    iteration; the same weights as now keep the version) or refused with the screener's
    reasons (``version`` is the one that keeps bidding; ``uploaded_id`` the refused one)."""

    round: int
    outcome: Literal["accepted", "refused"]
    accepted: bool
    reasons: list[ReasonPublic]
    version: int
    model_id: int
    parent_id: int
    uploaded_id: int | None


class JobCreate(_Input):
    """Start an experiment; ``params`` are the options of that kind (names with underscores or,
    as on the command line, dashes; lists as JSON arrays), checked by the kind's config."""

    kind: JobKind
    params: dict[str, Any] = Field(default_factory=dict)

    @classmethod
    def __get_pydantic_json_schema__(
        cls, core_schema: CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        """One alternative per kind, its ``params`` the schema of the kind's config (bounds
        included), so the document says exactly what each kind accepts."""
        alternatives = [
            {
                "type": "object",
                "title": f"{name} job",
                "properties": {
                    "kind": {"const": name},
                    "params": config_schema(kind.config_class()),
                },
                "required": ["kind"],
                "additionalProperties": False,
            }
            for name, kind in KINDS.items()
        ]
        return {"title": "JobCreate", "description": cls.__doc__, "oneOf": alternatives}


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
    next_cursor: int | None


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
    next_cursor: int | None


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
    next_cursor: int | None


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
