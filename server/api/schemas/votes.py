"""A patron's vote in one auction iteration, explained by its named neurons."""

from __future__ import annotations

from typing import Any, Literal

from server.api.schemas.common import ReasonPublic, Schema


class SensorPublic(Schema):
    """The external sensor after its activations."""

    PG: float
    """The high-price neuron (price too high)."""
    SZ: float
    """The size neuron (a big fish)."""
    LSR: float
    """The limited-supply-rush neuron (many bought last round: the f input)."""
    ST: float
    """The sub-type neuron (the preferred sub-type)."""


class DecisionPublic(Schema):
    """The decision logits; the vote is the largest."""

    B: float
    """Buy."""
    L: float
    """Hold (want a lower price)."""
    Q: float
    """Quit."""


class JudgementPublic(Schema):
    """The prefrontal cortex's judgements of the decision, read from the softmax of the
    sensor and the decision (before their tanh): what its verdicts weigh."""

    PGL: float
    """Holding at a high price (a right decision: feeds T)."""
    BC: float
    """Buying cheap (a right decision: feeds T)."""
    FQ: float
    """Quitting a good, wanted fish (a wrong decision: feeds F)."""


class PfcPublic(Schema):
    """The prefrontal cortex's self-judgement of the decision."""

    T: float
    """The verdict 'right'."""
    F: float
    """The verdict 'wrong'."""


class PatronVotePublic(Schema):
    """One patron's vote in an iteration and the neurons behind it, on row 0 (the row that
    decides), each averaged over its D_ic copies as its vote was."""

    model_id: int
    """The patron, as in the auction's ``model_ids``."""
    participant: str
    version: int
    """The version that bid (a remote auction's patron may bid with a later one than it
    entered with)."""
    version_id: int
    """That version's stored model (``GET /models/{version_id}``)."""
    fine_tuned_after: int | None
    """The iteration after which a server-mode auction last fine-tuned this patron inside the
    market (its re-screening keeping the result): the neurons here are those fine-tuned
    weights', which ``.../votes/{model_id}/weights`` gives. None: it bid with its version's own
    weights."""
    weights_kept: bool
    """False for a vote after a fine-tuning inside the market of an auction created before the
    server kept fine-tuned weights: its neurons are those of weights no longer known
    (``fine_tuned_after`` is then None, and ``.../weights`` answers 404)."""
    vote: Literal["buy", "hold", "quit"]
    sensor: SensorPublic
    decision: DecisionPublic
    judgement: JudgementPublic | None
    """None for an iteration committed before the judgements were kept with its votes."""
    pfc: PfcPublic


class VoteExplanationPublic(PatronVotePublic):
    """Why a patron voted as it did in one iteration."""

    auction_id: int
    iteration: int
    row: dict[str, float]
    """Row 0's inputs by name: price, length, weight, gill, st1, st2, st3, buy_fraction."""


class IterationVotesPublic(Schema):
    """Every vote of one committed iteration, in patron order: the patrons still in it."""

    auction_id: int
    iteration: int
    row: dict[str, float]
    """Row 0's inputs by name: price, length, weight, gill, st1, st2, st3, buy_fraction."""
    votes: list[PatronVotePublic]


class MarketFineTuningPublic(Schema):
    """One fine-tuning of a patron inside the market of a server-mode auction."""

    after: int
    """The iteration after which it fine-tuned."""
    kept: bool
    """Whether its re-screening kept the result (else the patron bid on with the weights it
    had: the screener refused them, or they passed a bar by less than the review margin)."""
    reasons: list[ReasonPublic]
    """Why its re-screening did not keep the result, in the screener's words (empty when it
    did, and for a refusal stored before this server kept the reasons)."""


class VotedWeightsPublic(Schema):
    """The weights that cast one vote: a manifest as ``POST /submit`` takes it."""

    auction_id: int
    iteration: int
    model_id: int
    """The patron, as in the auction's ``model_ids``."""
    participant: str
    version: int
    version_id: int
    """The stored version the weights come from (``GET /models/{version_id}``)."""
    fine_tuned_after: int | None
    """As in the vote: the iteration after which the market fine-tuned these weights from that
    version's (None: they are the version's own)."""
    fine_tunings: list[MarketFineTuningPublic]
    """Every fine-tuning of this patron inside the market before this iteration, kept or not,
    in order (empty outside server-mode fine-tuning)."""
    manifest: dict[str, Any]
