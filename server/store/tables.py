"""Database tables (SQLAlchemy 2 typed models). The schema itself is created by migrations."""

from __future__ import annotations

import re
import unicodedata
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
    true,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.engine.default import DefaultExecutionContext
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

NAMING = {  # stable constraint names, so migrations can refer to them on every backend
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


LEASE_OWNER_LENGTH = 96
"""Longest lease owner id (host name, process id, random suffix)."""


def utcnow() -> datetime:
    """Aware UTC now."""
    return datetime.now(UTC)


class UtcDateTime(TypeDecorator[datetime]):
    """A timestamp stored in UTC and always read back timezone-aware (SQLite drops the zone)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.astimezone(UTC) if value.tzinfo else value.replace(tzinfo=UTC)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)


NAME_KEY_LENGTH = 128
"""Longest stored name key (a folded name can be longer than the name)."""


_LOOKALIKE = str.maketrans({"1": "l", "i": "l", "|": "l", "0": "o", "_": "-", ".": "-"})
"""Characters a reader takes for one another in a name: I, l and 1; O and 0; the separators."""


_LEADING_ZEROS = re.compile(r"(^|[-_.])[0o]+(?=[0-9]|[1il|][0-9oil|]*(?:[-_.]|$))")
"""Zeros or Os leading a number at a part's start: a digit follows, or the part reads as a
number (its other characters I, l, 1, O, 0 or digits: ``0l``, ``OI``, but not ``olive``)."""


def participant_key(name: str) -> str:
    """What makes two participant names the same, as a person reads them: their NFKC form,
    case-folded, with the characters one takes for one another made one (I, l and 1; O and 0;
    rn and m; vv and w; cl and d; -, _ and ., and a run of them), separators at the ends and
    zeros leading a number (at the start or after a separator) left out: ``honest-I``,
    ``honest_1``, ``Honest-01``, ``honest-0l`` and ``honest-1`` are one name, which belongs to
    whoever registered one of them first; so are ``dave`` and ``clave``."""
    folded = unicodedata.normalize("NFKC", name).casefold()
    # zeros (or an O) leading a number: at the name's start or after a separator only, so
    # that agent-l01 still reads as agent-101, not as agent-11; a number is a digit next, or
    # a part made of characters that read as digits (honest-0l is honest-01), not a word
    folded = _LEADING_ZEROS.sub(r"\1", folded)
    read = folded.translate(_LOOKALIKE)
    for pair, letter in _READ_AS_ONE:
        read = read.replace(pair, letter)
    return re.sub(r"-+", "-", read).strip("-") or read


_READ_AS_ONE = (("rn", "m"), ("vv", "w"), ("cl", "d"))
"""Two letters a reader takes for one (after ``_LOOKALIKE``: c1 and cI read cl too)."""


def rekey_participants(connection: Any) -> None:
    """Compute every stored participant's ``name_key`` (the migrations' that add it or fold
    more). Participants stored before whose names fold to one key keep working under their
    exact names: the first registered keeps the key, each later one gets it suffixed with
    ``#<id>`` (which no name can fold to). The table as those revisions know it, not as the
    model describes it now."""
    from sqlalchemy import bindparam, column, select, table, update

    participants = table("participants", column("id"), column("name"), column("name_key"))
    rows = connection.execute(
        select(participants.c.id, participants.c.name).order_by(participants.c.id)
    ).all()
    taken: set[str] = set()
    keys = []
    for participant_id, name in rows:
        key = participant_key(name)
        if key in taken:
            key = f"{key}#{participant_id}"
        taken.add(key)
        keys.append({"row_id": participant_id, "key": key})
    set_key = (
        update(participants)
        .where(participants.c.id == bindparam("row_id"))
        .values(name_key=bindparam("key"))
    )
    if keys:  # through keys no name folds to first, so that no update meets a unique key
        connection.execute(
            set_key, [{"row_id": k["row_id"], "key": f"#{k['row_id']}"} for k in keys]
        )
        connection.execute(set_key, keys)


def _name_key_default(context: DefaultExecutionContext) -> str:
    parameters: dict[str, Any] = context.get_current_parameters()  # type: ignore[no-untyped-call]
    return participant_key(parameters["name"])


class Participant(Base):
    """Whoever submits models under one name; holds the hash of its submission token."""

    __tablename__ = "participants"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    name_key: Mapped[str] = mapped_column(
        String(NAME_KEY_LENGTH), unique=True, default=_name_key_default
    )
    """``participant_key(name)``: unique, so names differing only in case, Unicode form or
    look-alike characters are one participant (set from ``name`` on insert)."""
    token_hash: Mapped[str] = mapped_column(String(64), index=True)
    """SHA-256 of its token, indexed: the per-client limits tell a real token from a made-up
    one by it."""
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)

    versions: Mapped[list[ModelVersion]] = relationship(back_populates="participant")


def _status_of_verdict(context: Any) -> str:
    """A version written without a status: accepted or refused, as its ``accepted`` says."""
    return "accepted" if context.get_current_parameters()["accepted"] else "refused"


class ModelVersion(Base):
    """One submitted manifest of a participant, with the screener's verdict."""

    __tablename__ = "model_versions"
    __table_args__ = (UniqueConstraint("participant_id", "version"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), index=True)
    version: Mapped[int] = mapped_column(Integer)
    manifest: Mapped[dict[str, Any]] = mapped_column(JSON)
    accepted: Mapped[bool] = mapped_column(Boolean)
    """True only while ``status`` is accepted (kept: every auction query reads it)."""
    reasons: Mapped[list[dict[str, str]]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    status: Mapped[str] = mapped_column(String(8), index=True, default=_status_of_verdict)
    """accepted | refused | held (``server.store.status.ModelStatus``); by default what
    ``accepted`` says."""
    evidence: Mapped[list[dict[str, Any]] | None] = mapped_column(
        JSON(none_as_null=True), nullable=True
    )
    """The screener's ``Evidence`` (null for versions stored before it was kept)."""
    # A version uploaded in a remote fine-tuning round: the version it was fine-tuned from,
    # and the auction and round (null for versions sent to /submit).
    parent_id: Mapped[int | None] = mapped_column(ForeignKey("model_versions.id"), nullable=True)
    auction_id: Mapped[int | None] = mapped_column(ForeignKey("auctions.id"), nullable=True)
    round: Mapped[int | None] = mapped_column(Integer, nullable=True)

    participant: Mapped[Participant] = relationship(back_populates="versions")


class Review(Base):
    """A model's audit log: an inspector's decision on a held model (with the evidence shown),
    or its participant's appeal of a refusal (``inspector`` is then the participant's name)."""

    __tablename__ = "reviews"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    model_id: Mapped[int] = mapped_column(ForeignKey("model_versions.id"), index=True)
    decision: Mapped[str] = mapped_column(String(8))
    """admit | refuse | appeal (``server.store.status.ReviewDecision``)."""
    inspector: Mapped[str] = mapped_column(String(64))
    note: Mapped[str] = mapped_column(Text)
    at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    evidence: Mapped[list[dict[str, Any]] | None] = mapped_column(
        JSON(none_as_null=True), nullable=True
    )


class Auction(Base):
    """One fish sale: its settings, where it stands, and the market checkpoint to resume from."""

    __tablename__ = "auctions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    status: Mapped[str] = mapped_column(String(16), index=True)
    n_initial: Mapped[int] = mapped_column(Integer)
    rarity: Mapped[float | None] = mapped_column(Float, nullable=True)
    max_iterations: Mapped[int] = mapped_column(Integer)
    fine_tune: Mapped[bool] = mapped_column(Boolean)
    fine_tune_mode: Mapped[str] = mapped_column(String(8), default="server")
    """"server": the worker fine-tunes the patrons; "remote": the participants do, in rounds."""
    fine_tune_rounds: Mapped[int] = mapped_column(Integer, default=4)
    round_deadline_s: Mapped[float] = mapped_column(Float, default=10.0)
    keeps_tuned_weights: Mapped[bool] = mapped_column(Boolean, server_default=true())
    """Whether its fine-tunings inside the market are kept (``TunedWeights``): false for the
    auctions created before the server kept them."""
    buy_fraction: Mapped[str] = mapped_column(String(8), default="all")
    """The market's buy-fraction rule: "all" voters or the "staying" ones."""
    n_rows: Mapped[int] = mapped_column(Integer, server_default="64")
    """Item rows each patron scores per iteration (and a remote round publishes): 64, the
    reference's, or the paper's 16."""
    seed: Mapped[int] = mapped_column(Integer)
    iteration: Mapped[int] = mapped_column(Integer, default=0)
    price: Mapped[float] = mapped_column(Float)
    n_available: Mapped[int] = mapped_column(Integer)
    checkpoint: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True, deferred=True)
    stop_reason: Mapped[str | None] = mapped_column(String(64), nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    lease_owner: Mapped[str | None] = mapped_column(String(LEASE_OWNER_LENGTH), nullable=True)
    """The API process playing the auction (``server.work.runner``), while its lease lasts."""
    lease_expires: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)
    enroll_until: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)
    """While pending: until when participants may add their models as patrons (``POST
    /auctions/{id}/patrons``); null once its patrons are fixed (or if it never enrolled)."""
    next_step_at: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True, index=True)
    """When the auction's next step is due (``server.auctions.steps``): at once while it plays, its
    round's deadline while a remote round is open (sooner once every asked patron answered);
    null once it has ended."""

    patrons: Mapped[list[AuctionPatron]] = relationship(order_by="AuctionPatron.position")
    history: Mapped[list[AuctionIteration]] = relationship(order_by="AuctionIteration.iteration")
    purchases: Mapped[list[Purchase]] = relationship(order_by="Purchase.id")
    quits: Mapped[list[Quit]] = relationship(order_by="Quit.id")


class AuctionPatron(Base):
    """The ordered patron list of an auction: patron index ``position`` is model ``model_id``."""

    __tablename__ = "auction_patrons"

    auction_id: Mapped[int] = mapped_column(ForeignKey("auctions.id"), primary_key=True)
    position: Mapped[int] = mapped_column(Integer, primary_key=True)
    model_id: Mapped[int] = mapped_column(ForeignKey("model_versions.id"), index=True)
    current_model_id: Mapped[int | None] = mapped_column(
        ForeignKey("model_versions.id"), nullable=True
    )
    """The version bidding now, after remote fine-tuning rounds (null: ``model_id``)."""


class AuctionIteration(Base):
    """One committed auction round: the price asked, fish left, and the row-0 votes."""

    __tablename__ = "auction_iterations"
    __table_args__ = (UniqueConstraint("auction_id", "iteration"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    auction_id: Mapped[int] = mapped_column(ForeignKey("auctions.id"))
    iteration: Mapped[int] = mapped_column(Integer)
    price: Mapped[float] = mapped_column(Float)
    n_available: Mapped[int] = mapped_column(Integer)
    votes: Mapped[dict[str, int]] = mapped_column(JSON)
    row_votes: Mapped[dict[str, int]] = mapped_column(JSON)
    next_price: Mapped[float] = mapped_column(Float)
    n_available_after: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    explanations: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True, default=None)
    """Every voter's neurons on row 0 (``IterationRecord.explained``, patrons by model id);
    null for iterations committed before explanations were kept."""


class TunedWeights(Base):
    """A patron's fine-tuning inside the market of a server-mode auction, after ``iteration``:
    kept (its re-screening accepted the weights, which bid from the next iteration on, until
    the next kept row) or refused (the patron bid on with the weights it had before)."""

    __tablename__ = "tuned_weights"

    auction_id: Mapped[int] = mapped_column(ForeignKey("auctions.id"), primary_key=True)
    model_id: Mapped[int] = mapped_column(ForeignKey("model_versions.id"), primary_key=True)
    """The patron, by the version it entered with (as its votes are kept)."""
    iteration: Mapped[int] = mapped_column(Integer, primary_key=True)
    kept: Mapped[bool] = mapped_column(Boolean)
    manifest: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True), nullable=True)
    """The weights kept (null for a refused fine-tuning)."""
    reasons: Mapped[list[dict[str, str]] | None] = mapped_column(
        JSON(none_as_null=True), nullable=True
    )
    """Why the re-screening refused it: the screener's reasons, each ``{rule, neuron,
    message}`` (null when kept, and for refusals stored before the reasons were kept)."""


class Purchase(Base):
    """A patron bought a fish; a patron buys at most once per auction."""

    __tablename__ = "purchases"
    __table_args__ = (UniqueConstraint("auction_id", "model_id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    auction_id: Mapped[int] = mapped_column(ForeignKey("auctions.id"))
    model_id: Mapped[int] = mapped_column(ForeignKey("model_versions.id"), index=True)
    price: Mapped[float] = mapped_column(Float)
    iteration: Mapped[int] = mapped_column(Integer)


class Quit(Base):
    """A patron left the auction without buying."""

    __tablename__ = "quits"
    __table_args__ = (UniqueConstraint("auction_id", "model_id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    auction_id: Mapped[int] = mapped_column(ForeignKey("auctions.id"))
    model_id: Mapped[int] = mapped_column(ForeignKey("model_versions.id"), index=True)
    iteration: Mapped[int] = mapped_column(Integer)


class FineTuneRound(Base):
    """A remote fine-tuning round: published after ``iteration``, open until every asked patron
    has answered or ``deadline`` (absolute, UTC) has passed; closed in the transaction that
    applies its answers to the market checkpoint."""

    __tablename__ = "fine_tune_rounds"
    __table_args__ = (UniqueConstraint("auction_id", "round"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    auction_id: Mapped[int] = mapped_column(ForeignKey("auctions.id"))
    round: Mapped[int] = mapped_column(Integer)
    """1 for the round after iteration 0, and so on."""
    iteration: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(8))
    """open | closed."""
    opened_at: Mapped[datetime] = mapped_column(UtcDateTime)
    deadline: Mapped[datetime] = mapped_column(UtcDateTime)
    closed_at: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)
    given_back_at: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)
    """When a database outage's time was last given back (``deadline`` pushed back): a
    replica that met the same outage gives it no second time."""
    rows: Mapped[list[list[float]]] = mapped_column(JSON)
    fine_tune_seed: Mapped[int] = mapped_column(BigInteger)
    augmentation_seed: Mapped[int] = mapped_column(BigInteger)
    asked: Mapped[list[int]] = mapped_column(JSON)
    """Positions of the patrons asked (the active ones)."""
    bytes_published: Mapped[int] = mapped_column(BigInteger, default=0)
    """Bodies of the ``GET .../rounds/current`` answers that carried this round."""

    answers: Mapped[list[FineTuneAnswer]] = relationship(order_by="FineTuneAnswer.position")


class FineTuneAnswer(Base):
    """A patron's outcome in a round: pending | accepted | refused | held (re-screening) |
    late | missing.

    Written as ``pending`` (with the uploaded manifest) as soon as an upload in time is read and
    checked, so the deadline is judged at arrival; its verdict then makes it accepted or
    refused (by the API, or by the step that closes the round). A late upload is written late,
    a silent patron missing when the round closes. ``model_id`` is the version the patron bids
    with after the round.
    """

    __tablename__ = "fine_tune_answers"
    __table_args__ = (UniqueConstraint("round_id", "position"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    round_id: Mapped[int] = mapped_column(ForeignKey("fine_tune_rounds.id"))
    position: Mapped[int] = mapped_column(Integer)
    outcome: Mapped[str] = mapped_column(String(8))
    model_id: Mapped[int] = mapped_column(ForeignKey("model_versions.id"))
    uploaded_id: Mapped[int | None] = mapped_column(ForeignKey("model_versions.id"), nullable=True)
    """The version stored from the upload (accepted or refused; null if none was stored)."""
    body_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)
    answer: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True), nullable=True)
    """The response body given to the upload (a repeat with the same bytes gets it again)."""
    manifest: Mapped[dict[str, Any] | None] = mapped_column(
        JSON(none_as_null=True), nullable=True, deferred=True
    )
    """A pending upload's manifest, until its verdict stores it as a version."""
    bytes_in: Mapped[int] = mapped_column(BigInteger, default=0)
    bytes_out: Mapped[int] = mapped_column(BigInteger, default=0)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class Job(Base):
    """A background experiment: kind, validated params, status, progress, result, artifacts.

    ``attempt`` counts how often a worker claimed the job; a worker writes only while the row
    still carries its own attempt number, so a stale worker can never overwrite a newer one.
    """

    __tablename__ = "jobs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    kind: Mapped[str] = mapped_column(String(32))
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    status: Mapped[str] = mapped_column(String(16), index=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    message: Mapped[str] = mapped_column(String(200), default="")
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True), nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    artifacts: Mapped[list[str]] = mapped_column(JSON, default=list)
    attempt: Mapped[int] = mapped_column(Integer, default=0)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    lease_owner: Mapped[str | None] = mapped_column(String(LEASE_OWNER_LENGTH), nullable=True)
    """The API process running the job (``server.work.runner``), while its lease lasts."""
    lease_expires: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)


class RateEvent(Base):
    """One event that a quota counts: a new version, a registration or a screener refusal, by
    a participant (``participant:<name>``) or a client address (``address:<host>``). Kept in
    the database so that every API process sees the same counts; pruned past the longest
    window."""

    __tablename__ = "rate_events"
    __table_args__ = (Index("ix_rate_events_subject_kind_at", "subject", "kind", "created_at"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    subject: Mapped[str] = mapped_column(String(160))
    kind: Mapped[str] = mapped_column(String(16))
    """version | registration | refusal."""
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, index=True)
