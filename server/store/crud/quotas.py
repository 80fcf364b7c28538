"""The quota events of ``POST /submit`` (``rate_events``): counted per subject and kind over a
day, an hour and a minute, a participant's recent events in order, inserted, pruned."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import (
    ColumnElement,
    Connection,
    bindparam,
    case,
    delete,
    func,
    insert,
    select,
    text,
)
from sqlalchemy.orm import Session

from server.store.tables import RateEvent


@dataclass(frozen=True)
class RateCount:
    """The events of one subject and kind in the last day, hour and minute, with the oldest of
    each window (None where the window holds none)."""

    day: int
    hour: int
    minute: int
    oldest: dict[str, datetime]
    """``day``, ``hour``, ``minute`` → the oldest event in it."""


def _since(name: str) -> ColumnElement[bool]:
    return RateEvent.created_at >= bindparam(name)


_COUNTS = (
    select(
        RateEvent.subject,
        RateEvent.kind,
        func.count(),
        func.sum(case((_since("hour"), 1), else_=0)),
        func.sum(case((_since("minute"), 1), else_=0)),
        func.min(RateEvent.created_at),
        func.min(case((_since("hour"), RateEvent.created_at))),
        func.min(case((_since("minute"), RateEvent.created_at))),
    )
    .where(RateEvent.subject.in_(bindparam("subjects", expanding=True)), _since("day"))
    .group_by(RateEvent.subject, RateEvent.kind)
)
_RECENT = (
    select(RateEvent.kind, RateEvent.created_at)
    .where(
        RateEvent.subject == bindparam("subject"),
        RateEvent.kind.in_(bindparam("kinds", expanding=True)),
        _since("since"),
    )
    .order_by(RateEvent.created_at)
)


def rate_counts(
    session: Session, *, subjects: Sequence[str], windows: dict[str, datetime]
) -> dict[tuple[str, str], RateCount]:
    """(subject, kind) → its events since each of ``windows`` (``day``, ``hour``, ``minute`` →
    the window's start), in one query; pairs without events are left out."""
    rows = session.connection().execute(_COUNTS, {"subjects": list(subjects), **windows})
    return {
        (subject, kind): RateCount(
            int(day),
            int(hour or 0),
            int(minute or 0),
            {name: _aware(t, windows["day"]) for name, t in zip(windows, oldest, strict=True) if t},
        )
        for subject, kind, day, hour, minute, *oldest in rows
    }


def recent_events(
    session: Session, *, subject: str, kinds: Sequence[str], since: datetime
) -> list[tuple[str, datetime]]:
    """(kind, time) of the subject's events of ``kinds`` since ``since``, oldest first."""
    rows = session.connection().execute(
        _RECENT, {"subject": subject, "kinds": list(kinds), "since": since}
    )
    return [(kind, _aware(at, since)) for kind, at in rows]


def insert_rate_events(
    session: Session | Connection, *, events: Sequence[tuple[str, str]], now: datetime
) -> None:
    """Insert (subject, kind) events that happened ``now`` (in a session's transaction, or a
    connection's)."""
    rows = [{"subject": subject, "kind": kind, "created_at": now} for subject, kind in events]
    if rows:
        connection = session.connection() if isinstance(session, Session) else session
        connection.execute(insert(RateEvent), rows)


def prune_rate_events(session: Session, *, before: datetime) -> None:
    """Delete the events older than ``before``."""
    session.execute(delete(RateEvent).where(RateEvent.created_at < before))


def _aware(value: datetime, like: datetime) -> datetime:
    """SQLite hands back naive UTC timestamps from aggregates; compare them as aware ones."""
    return value if value.tzinfo is not None else value.replace(tzinfo=like.tzinfo)


_LOCK_SUBJECT = text("SELECT pg_advisory_xact_lock(hashtextextended(:subject, 0))")


def lock_subject(session: Session, subject: str) -> None:
    """Hold ``subject`` (a quota's, or a cap's such as the live auctions') until the
    transaction ends, so that concurrent requests count one another's rows: on PostgreSQL a
    transaction-level advisory lock on the subject; SQLite serialises writers already."""
    if session.get_bind().dialect.name == "postgresql":
        session.execute(_LOCK_SUBJECT, {"subject": subject})
