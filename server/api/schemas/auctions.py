"""Bodies of auctions: ``POST /auctions``, ``GET /auctions/{id}``, the auction list, and the
payloads of an auction's event stream (the ``data`` of each Server-Sent Event, as JSON)."""

from __future__ import annotations

from collections import Counter
from datetime import datetime
from typing import Annotated, Any

from pydantic import ConfigDict, Field, JsonValue, field_validator

from server.api.schemas.common import MAX_SEED, RowId, Schema, StrictInput
from server.api.schemas.rounds import FineTuneModeName, FineTuneRoundPublic
from server.store.status import AuctionStatus
from sim.market import BuyFractionRule, MarketConfig

MAX_PATRONS = 10_000
"""Patrons of an auction, at most."""
MAX_ENROLLMENT_S = 86_400.0
"""The longest enrollment: a day."""
MIN_ENROLLMENT_S = 1.0
"""The shortest enrollment (above none): a participant's join takes a request."""
ROUND_DEADLINE_S = (0.5, 300.0)
"""Bounds of a remote auction's ``round_deadline_s``: how long a round waits at most."""
MAX_ROWS = 256
"""Item rows of an auction, at most (as a study's)."""
MAX_FINE_TUNE_ROUNDS = 64
"""Fine-tuning rounds of an auction, at most (each may wait a whole deadline)."""


_REMOTE: dict[str, JsonValue] = {
    "properties": {"fine_tune_mode": {"const": "remote"}},
    "required": ["fine_tune_mode"],
}
"""JSON Schema: a remote auction."""
_FINE_TUNES: dict[str, JsonValue] = {
    "properties": {"fine_tune": {"const": True}},
    "required": ["fine_tune"],
}
"""JSON Schema: an auction that fine-tunes in the market."""


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


class AuctionCreate(StrictInput):
    """Start an auction: exactly one of ``n_fish`` or ``rarity`` (fish = int(rarity × patrons)).

    ``fine_tune_mode`` "remote": the participants fine-tune their own patrons over HTTP, in
    rounds after each of the first ``fine_tune_rounds`` iterations, each round waiting at most
    ``round_deadline_s``. A remote auction fine-tunes (``fine_tune`` may be left out; false is
    refused); ``round_deadline_s`` belongs to remote auctions only. ``fine_tune_rounds`` belongs
    to auctions that fine-tune (in the market or remote), and is at least 1 there."""

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
                {  # fine-tuning rounds belong to auctions that fine-tune, 1 at least
                    "if": {"anyOf": [_REMOTE, _FINE_TUNES]},
                    "then": {"properties": {"fine_tune_rounds": {"minimum": 1}}},
                    "else": {"not": {"required": ["fine_tune_rounds"]}},
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
    buy_fraction: BuyFractionRule = MarketConfig.buy_fraction
    """Whom a row's buy fraction f counts: "all" voters (the paper's) or the "staying" ones,
    buyers and holders (quitting does not lower f)."""
    rows: Annotated[int, Field(ge=1, le=MAX_ROWS)] = MarketConfig.n_rows
    """Item rows each patron scores per iteration, the prototype fish and its variations (and
    the rows a remote round publishes): 64, the reference's, which made the paper's figures,
    or the paper's text's 16 (``srd auction-study --rows``)."""
    enrollment_s: Annotated[
        float,
        Field(
            ge=0,
            le=MAX_ENROLLMENT_S,
            allow_inf_nan=False,
            json_schema_extra={
                "not": {"exclusiveMinimum": 0, "exclusiveMaximum": MIN_ENROLLMENT_S}
            },
        ),
    ] = 0.0
    """Seconds the auction stays pending, taking patrons: each participant may add one accepted
    model of its own (``POST /auctions/{id}/patrons``); its patrons are then the models named in
    ``model_ids`` (none if left out) and those that joined, and a rarity's fish are counted when
    the enrollment ends. 0: the patrons are fixed now."""

    @field_validator("model_ids")
    @classmethod
    def _distinct(cls, ids: list[int] | None) -> list[int] | None:
        """A patron takes part once."""
        if ids is not None and len(set(ids)) != len(ids):
            twice = sorted(i for i, n in Counter(ids).items() if n > 1)
            raise ValueError(f"model ids listed more than once: {twice[:20]}")
        return ids

    @field_validator("enrollment_s")
    @classmethod
    def _joinable(cls, seconds: float) -> float:
        """An enrollment somebody can join: none (0), or a second at least."""
        if 0 < seconds < MIN_ENROLLMENT_S:
            raise ValueError(
                f"an enrollment of {seconds:g} s ends before anybody can join: give 0 (the "
                f"patrons are fixed now) or at least {MIN_ENROLLMENT_S:g} s"
            )
        return seconds

    @field_validator("n_fish", "rarity", "model_ids", mode="before")
    @classmethod
    def _absent_not_null(cls, value: Any) -> Any:
        """An option left out is absent; ``null`` is not one of its values."""
        if value is None:
            raise ValueError("must not be null: leave it out instead")
        return value


class AuctionCreated(Schema):
    auction_id: int


class Votes(Schema):
    """Row-0 decisions of the patrons still in the auction."""

    buy: int
    hold: int
    quit: int


class IterationPublic(Schema):
    """One auction round: price asked and fish left at its start, the votes, what followed."""

    iteration: int
    price: float
    n_available: int
    votes: Votes
    row_votes: Votes
    next_price: float
    n_available_after: int


class BuyerPublic(Schema):
    """A patron who bought a fish: the version that bid, its participant, price and round."""

    model_id: int
    price: float
    iteration: int
    participant: str
    version: int
    version_id: int
    """The stored version that bid (``GET /models/{version_id}``): ``model_id`` itself unless a
    remote round admitted a fine-tuned one before the patron left."""


class QuitterPublic(Schema):
    """A patron who left without buying: the version that quit, its participant and round."""

    model_id: int
    participant: str
    version: int
    iteration: int
    version_id: int
    """The stored version that bid (``GET /models/{version_id}``): ``model_id`` itself unless a
    remote round admitted a fine-tuned one before the patron left."""


class AuctionPublic(Schema):
    """An auction as it stands; ``history`` grows by one committed row per iteration."""

    id: int
    status: AuctionStatus
    iteration: int
    price: float
    n_available: int
    n_initial: int
    n_sold: int
    """Fish sold so far (``n_initial`` − ``n_available``), as the list and the end event name it."""
    history: list[IterationPublic]
    buyers: list[BuyerPublic]
    quitters: list[int]
    quitter_details: list[QuitterPublic]
    """``quitters`` with the participant, version and round of each."""
    stop_reason: str | None
    n_patrons: int
    model_ids: list[int]
    participants: list[str]
    """The participant of each patron, aligned with ``model_ids``."""
    revenue: float
    mean_price: float | None = None
    """The mean price paid (null: nobody bought)."""
    purchase_rate: float | None = None
    """Fish sold / fish on sale (the paper's purchase rate; null with no fish counted yet)."""
    buyer_fraction: float | None = None
    """Buyers / patrons (what the reference code plotted; null with no patrons yet)."""
    last_price: float | None = None
    """The price asked in the last committed iteration (``price`` is the one to ask next:
    after the end, a price never asked); null before the first."""
    rarity: float | None
    max_iterations: int
    fine_tune: bool
    seed: int
    error: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    fine_tune_mode: FineTuneModeName = "server"
    fine_tune_rounds: int | None = 4
    """How many iterations are followed by fine-tuning (null: the auction does not
    fine-tune)."""
    round_deadline_s: float | None = None
    """Remote auctions: how long a round waits at most (null in server mode: no rounds)."""
    buy_fraction: BuyFractionRule = MarketConfig.buy_fraction
    rows: int = MarketConfig.n_rows
    """Item rows each patron scores per iteration (and a remote round publishes)."""
    fine_tuning: list[FineTuneRoundPublic] = Field(default_factory=list)
    """Remote auctions: every fine-tuning round with each asked patron's outcome."""
    current_model_ids: list[int] = Field(default_factory=list)
    """Remote auctions: the version each patron bids with now, aligned with ``model_ids``."""
    enroll_until: datetime | None = None
    """While it takes patrons (``POST /auctions/{id}/patrons``): until when; else null."""


class PatronJoin(StrictInput):
    """A participant's accepted model, to bid in an enrolling auction."""

    model_id: RowId


class PatronJoined(Schema):
    """The model is a patron of the auction: its position in ``model_ids``."""

    auction_id: int
    model_id: int
    position: int
    n_patrons: int
    enroll_until: datetime | None
    """When the enrollment ends and the auction starts."""


class AuctionSummaryPublic(Schema):
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


class AuctionPage(Schema):
    items: list[AuctionSummaryPublic]
    next_cursor: int | None


class PatronPublic(Schema):
    """A patron: its model id and the participant and version behind it."""

    model_id: int
    participant: str
    version: int
    version_id: int
    """The stored version that bid (``GET /models/{version_id}``): ``model_id`` itself unless a
    remote round admitted a fine-tuned one before the patron left."""


class RoundPurchasePublic(PatronPublic):
    price: float


class IterationEvent(IterationPublic):
    """``event: iteration`` (``id`` = ``iteration``): one committed iteration, its purchases and
    quits."""

    purchases: list[RoundPurchasePublic]
    quits: list[PatronPublic]


class AuctionEndEvent(Schema):
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
