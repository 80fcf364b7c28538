"""A patron's vote in one auction iteration, explained by its named neurons."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel


class SensorPublic(BaseModel):
    """The external sensor after its activations."""

    PG: float
    """The high-price neuron (price too high)."""
    SZ: float
    """The size neuron (a big fish)."""
    LSR: float
    """The limited-supply-rush neuron (many bought last round: the f input)."""
    ST: float
    """The sub-type neuron (the preferred sub-type)."""


class DecisionPublic(BaseModel):
    """The decision logits; the vote is the largest."""

    B: float
    """Buy."""
    L: float
    """Hold (want a lower price)."""
    Q: float
    """Quit."""


class PfcPublic(BaseModel):
    """The prefrontal cortex's self-judgement of the decision."""

    T: float
    """The verdict 'right'."""
    F: float
    """The verdict 'wrong'."""


class VoteExplanationPublic(BaseModel):
    """Why a patron voted as it did: its neurons on row 0 of the iteration (the row that
    decides; the inputs are ``row``), each averaged over its D_ic copies as its vote was."""

    auction_id: int
    iteration: int
    model_id: int
    """The patron, as in the auction's ``model_ids``."""
    participant: str
    version: int
    """The version ``model_id`` names (a remote auction's patron may bid with a later one)."""
    vote: Literal["buy", "hold", "quit"]
    row: dict[str, float]
    """Row 0's inputs by name: price, length, weight, gill, st1, st2, st3, buy_fraction."""
    sensor: SensorPublic
    decision: DecisionPublic
    pfc: PfcPublic
