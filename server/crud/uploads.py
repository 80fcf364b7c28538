"""What an upload of a remote round is checked against, read for a whole batch of uploads at
once."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.engine import Connection
from sqlalchemy.orm import Session

from server.models import (
    Auction,
    AuctionPatron,
    FineTuneAnswer,
    FineTuneRound,
    ModelVersion,
    Participant,
)


@dataclass(frozen=True)
class UploadTarget:
    """What ``PUT /auctions/{id}/rounds/{round}/models/{model_id}`` checks before screening."""

    auction_status: str
    fine_tune_mode: str
    position: int | None
    """The model's position among the auction's patrons (None: not a patron)."""
    participant_id: int
    participant: str
    token_hash: str
    current_id: int
    """The version the patron bids with now."""
    current_version: int
    current_manifest: dict[str, Any]
    newest_round: int | None
    newest_status: str | None
    round_id: int | None
    """The path's round, if the auction has it."""
    round_status: str | None
    deadline: datetime | None
    asked: list[int]
    answer_outcome: str | None
    """This patron's answer in the path's round so far, if any."""
    answer_sha256: str | None
    answer: dict[str, Any] | None
    current_design: dict[str, Any] | None = None
    """The current version's design (``sim.market.design``), when the lookup worked it out."""


class UploadLookupError(LookupError):
    """The auction or the model of an upload's path does not exist (``field`` names which)."""

    def __init__(self, field: str) -> None:
        super().__init__(field)
        self.field = field


UploadKey = tuple[int, int, int]
"""(auction id, model id, round) of an upload's path."""


_Rows = dict[Any, Any]
"""Rows of one query of the batch (SQLAlchemy ``Row`` objects), keyed as the lookups need."""


@dataclass(frozen=True)
class _Batch:
    """Everything a batch of uploads is checked against, read once for the whole batch."""

    auctions: _Rows
    """auction id → status and fine-tuning mode"""
    owners: _Rows
    """model id → its participant"""
    patrons: _Rows
    """(auction id, model id) → the patron's position and current version id"""
    versions: _Rows
    """model id → version number and manifest (of the versions patrons bid with now)"""
    rounds: dict[int, _Rows]
    """auction id → round number → the round"""
    answers: _Rows
    """(round id, position) → the patron's answer so far"""


def upload_targets(
    session: Session, *, keys: Sequence[UploadKey]
) -> list[UploadTarget | UploadLookupError]:
    """What each upload of a batch is checked against, read in one transaction with six
    queries whatever the batch's size (the UploadLookupError of a path that names no auction
    or model)."""
    connection = session.connection()
    auction_ids = sorted({a for a, _, _ in keys})
    model_ids = sorted({m for _, m, _ in keys})
    auctions = _auctions(connection, auction_ids)
    owners = _owners(connection, model_ids)
    patrons = _patrons(connection, auction_ids, model_ids)
    versions = _versions(connection, sorted({_current_of(patrons, a, m) for a, m, _ in keys}))
    rounds = _rounds(connection, auction_ids)
    asked_ids = sorted({r.id for a, _, n in keys if (r := rounds.get(a, {}).get(n))})
    positions = sorted({p.position for p in patrons.values()})
    answers = _answers(connection, asked_ids, positions)
    batch = _Batch(auctions, owners, patrons, versions, rounds, answers)
    return [_target(batch, key) for key in keys]


def _auctions(connection: Connection, auction_ids: list[int]) -> _Rows:
    query = select(Auction.id, Auction.status, Auction.fine_tune_mode).where(
        Auction.id.in_(auction_ids)
    )
    return {row.id: row for row in connection.execute(query)}


def _owners(connection: Connection, model_ids: list[int]) -> _Rows:
    query = (
        select(
            ModelVersion.id,
            Participant.id.label("participant_id"),
            Participant.name,
            Participant.token_hash,
        )
        .join(Participant, Participant.id == ModelVersion.participant_id)
        .where(ModelVersion.id.in_(model_ids))
    )
    return {row.id: row for row in connection.execute(query)}


def _patrons(connection: Connection, auction_ids: list[int], model_ids: list[int]) -> _Rows:
    query = select(
        AuctionPatron.auction_id,
        AuctionPatron.model_id,
        AuctionPatron.position,
        AuctionPatron.current_model_id,
    ).where(AuctionPatron.auction_id.in_(auction_ids), AuctionPatron.model_id.in_(model_ids))
    return {(row.auction_id, row.model_id): row for row in connection.execute(query)}


def _current_of(patrons: _Rows, auction_id: int, model_id: int) -> int:
    """The id of the version the patron bids with now (the path's model when not a patron)."""
    patron = patrons.get((auction_id, model_id))
    if patron is None or patron.current_model_id is None:
        return model_id
    current: int = patron.current_model_id
    return current


def _versions(connection: Connection, version_ids: list[int]) -> _Rows:
    query = select(ModelVersion.id, ModelVersion.version, ModelVersion.manifest).where(
        ModelVersion.id.in_(version_ids)
    )
    return {row.id: row for row in connection.execute(query)}


def _rounds(connection: Connection, auction_ids: list[int]) -> dict[int, _Rows]:
    query = select(
        FineTuneRound.id,
        FineTuneRound.auction_id,
        FineTuneRound.round,
        FineTuneRound.status,
        FineTuneRound.deadline,
        FineTuneRound.asked,
    ).where(FineTuneRound.auction_id.in_(auction_ids))
    rounds: dict[int, _Rows] = {}
    for row in connection.execute(query):
        rounds.setdefault(row.auction_id, {})[row.round] = row
    return rounds


def _answers(connection: Connection, round_ids: list[int], positions: list[int]) -> _Rows:
    query = select(
        FineTuneAnswer.round_id,
        FineTuneAnswer.position,
        FineTuneAnswer.outcome,
        FineTuneAnswer.body_sha256,
        FineTuneAnswer.answer,
    ).where(FineTuneAnswer.round_id.in_(round_ids), FineTuneAnswer.position.in_(positions))
    return {(row.round_id, row.position): row for row in connection.execute(query)}


def _target(batch: _Batch, key: UploadKey) -> UploadTarget | UploadLookupError:
    """One upload's target, from the rows of its batch."""
    auction_id, model_id, number = key
    auction, owner = batch.auctions.get(auction_id), batch.owners.get(model_id)
    if auction is None or owner is None:
        return UploadLookupError("auction_id" if auction is None else "model_id")
    patron = batch.patrons.get((auction_id, model_id))
    current = batch.versions[_current_of(batch.patrons, auction_id, model_id)]
    mine = batch.rounds.get(auction_id, {})
    newest = mine[max(mine)] if mine else None
    asked = mine.get(number)
    answer = None
    if asked is not None and patron is not None:
        answer = batch.answers.get((asked.id, patron.position))
    return UploadTarget(
        auction_status=auction.status,
        fine_tune_mode=auction.fine_tune_mode,
        position=None if patron is None else patron.position,
        participant_id=owner.participant_id,
        participant=owner.name,
        token_hash=owner.token_hash,
        current_id=current.id,
        current_version=current.version,
        current_manifest=current.manifest,
        newest_round=None if newest is None else newest.round,
        newest_status=None if newest is None else newest.status,
        round_id=None if asked is None else asked.id,
        round_status=None if asked is None else asked.status,
        deadline=None if asked is None else asked.deadline,
        asked=[] if asked is None else list(asked.asked),
        answer_outcome=None if answer is None else answer.outcome,
        answer_sha256=None if answer is None else answer.body_sha256,
        answer=None if answer is None else answer.answer,
    )
