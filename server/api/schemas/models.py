"""Bodies of participants and model versions: ``POST /submit``, ``GET /models/{id}``, the model
list, ``GET /participants/{name}``."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from server.api.schemas.common import ReasonPublic


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


class ParticipantPublic(BaseModel):
    """A participant and its newest versions (all of them: ``GET /models?participant=``)."""

    name: str
    created_at: datetime
    n_versions: int
    versions: list[ModelSummaryPublic]
