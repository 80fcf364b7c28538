"""Quotas and rate limits on ``POST /submit``, counted in the database (``rate_events``), so
that every API process sharing the database enforces the same limits.

Per participant:
* new accepted versions per minute and per day (refused versions do not use them up);
* a cooldown after screener refusals, doubling with each refusal in a row (reset by an accepted
  version), so that nobody can probe the screener's thresholds quickly.

Per client address:
* registrations (first submissions of a new participant name) per day;
* new accepted versions per minute and per day, over all its participants;
* screener refusals per hour.

A submission over a limit is answered 429 with ``Retry-After`` and a message naming the limit
and its setting; its verdict is not revealed and nothing of it is stored. ``Throttle`` decides a
whole group of submissions (the group-commit writer's) with two queries, counting the earlier
submissions of the group as if stored.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import bindparam, case, delete, func, insert, select
from sqlalchemy.orm import Session

from server.config import Settings
from server.store.tables import RateEvent

VERSION, REGISTRATION, REFUSAL = "version", "registration", "refusal"
MINUTE, HOUR, DAY = timedelta(minutes=1), timedelta(hours=1), timedelta(days=1)
KEEP = DAY + HOUR
"""Events older than this count for no limit and are pruned."""


_PERSON = "participant:"


def participant_subject(name: str) -> str:
    return f"{_PERSON}{name}"


def address_subject(host: str) -> str:
    return f"address:{host}"


@dataclass(frozen=True)
class Limits:
    """The configured limits (``SRD_QUOTA_*`` settings)."""

    versions_per_minute: int
    versions_per_day: int
    address_versions_per_minute: int
    address_versions_per_day: int
    registrations_per_day: int
    address_refusals_per_hour: int
    cooldown_s: float
    cooldown_max_s: float

    @classmethod
    def of(cls, settings: Settings) -> Limits:
        return cls(
            versions_per_minute=settings.quota_versions_per_minute,
            versions_per_day=settings.quota_versions_per_day,
            address_versions_per_minute=settings.quota_address_versions_per_minute,
            address_versions_per_day=settings.quota_address_versions_per_day,
            registrations_per_day=settings.quota_registrations_per_day,
            address_refusals_per_hour=settings.quota_address_refusals_per_hour,
            cooldown_s=settings.refusal_cooldown_s,
            cooldown_max_s=settings.refusal_cooldown_max_s,
        )


@dataclass(frozen=True)
class Throttled:
    """A submission over a limit: the message names the limit, ``retry_after_s`` when it clears."""

    msg: str
    retry_after_s: int


_COUNTS = (
    select(
        RateEvent.subject,
        RateEvent.kind,
        func.count(),
        func.sum(case((RateEvent.created_at >= bindparam("hour"), 1), else_=0)),
        func.sum(case((RateEvent.created_at >= bindparam("minute"), 1), else_=0)),
        func.min(RateEvent.created_at),
        func.min(case((RateEvent.created_at >= bindparam("hour"), RateEvent.created_at))),
        func.min(case((RateEvent.created_at >= bindparam("minute"), RateEvent.created_at))),
    )
    .where(
        RateEvent.subject.in_(bindparam("subjects", expanding=True)),
        RateEvent.created_at >= bindparam("day"),
    )
    .group_by(RateEvent.subject, RateEvent.kind)
)
_RECENT = (
    select(RateEvent.subject, RateEvent.kind, RateEvent.created_at)
    .where(
        RateEvent.subject.in_(bindparam("subjects", expanding=True)),
        RateEvent.kind.in_((VERSION, REFUSAL)),
        RateEvent.created_at >= bindparam("since"),
    )
    .order_by(RateEvent.created_at)
)


@dataclass
class _Count:
    """Stored events of one (subject, kind) in the last day / hour / minute, with the oldest
    of each window (for Retry-After), plus the group's pending ones."""

    day: int = 0
    hour: int = 0
    minute: int = 0
    oldest: dict[str, datetime] = field(default_factory=dict)
    pending: list[datetime] = field(default_factory=list)

    def count(self, window: str) -> int:
        stored: int = {"day": self.day, "hour": self.hour, "minute": self.minute}[window]
        return stored + len(self.pending)

    def first(self, window: str) -> datetime | None:
        return self.oldest.get(window) or (self.pending[0] if self.pending else None)


class Throttle:
    """The limits applied to one group of submissions, in arrival order (see module doc)."""

    def __init__(
        self, session: Session, limits: Limits, now: datetime, subjects: list[str]
    ) -> None:
        self.limits, self.now = limits, now
        self.counts: dict[tuple[str, str], _Count] = defaultdict(_Count)
        self.recent: dict[str, list[tuple[str, datetime]]] = defaultdict(list)
        self.rows: list[dict[str, Any]] = []
        if not subjects:
            return
        connection = session.connection()
        windows = {"day": now - DAY, "hour": now - HOUR, "minute": now - MINUTE}
        for subject, kind, day, hour, minute, *oldest in connection.execute(
            _COUNTS, {"subjects": subjects, **windows}
        ):
            count = self.counts[(subject, kind)]
            count.day, count.hour, count.minute = int(day), int(hour or 0), int(minute or 0)
            count.oldest = {
                name: _aware(t, now) for name, t in zip(windows, oldest, strict=True) if t
            }
        # The cooldown reads participants' refusals in a row, never an address's: an address
        # shared by many participants would fetch all their versions of the last hour.
        people = [s for s in subjects if s.startswith(_PERSON)]
        since = now - timedelta(seconds=limits.cooldown_max_s)
        for subject, kind, at in connection.execute(_RECENT, {"subjects": people, "since": since}):
            self.recent[subject].append((kind, _aware(at, now)))

    def check(self, *, participant: str, address: str | None, new: bool) -> Throttled | None:
        """The first limit this submission would break, or None."""
        limits, person = self.limits, participant_subject(participant)
        checks: list[tuple[str, str, str, int, str, str]] = [
            (person, VERSION, "minute", limits.versions_per_minute, "versions per minute",
             "SRD_QUOTA_VERSIONS_PER_MINUTE"),
            (person, VERSION, "day", limits.versions_per_day, "versions per day",
             "SRD_QUOTA_VERSIONS_PER_DAY"),
        ]  # fmt: skip
        if address is not None:
            place = address_subject(address)
            checks += [
                (place, VERSION, "minute", limits.address_versions_per_minute,
                 "versions per minute from one address", "SRD_QUOTA_ADDRESS_VERSIONS_PER_MINUTE"),
                (place, VERSION, "day", limits.address_versions_per_day,
                 "versions per day from one address", "SRD_QUOTA_ADDRESS_VERSIONS_PER_DAY"),
                (place, REFUSAL, "hour", limits.address_refusals_per_hour,
                 "screener refusals per hour from one address",
                 "SRD_QUOTA_ADDRESS_REFUSALS_PER_HOUR"),
            ]  # fmt: skip
            if new:
                checks.append(
                    (place, REGISTRATION, "day", limits.registrations_per_day,
                     "registrations per day from one address", "SRD_QUOTA_REGISTRATIONS_PER_DAY")
                )  # fmt: skip
        span = {"minute": MINUTE, "hour": HOUR, "day": DAY}
        for subject, kind, window, limit, what, setting in checks:
            count = self.counts[(subject, kind)]
            if count.count(window) >= limit:
                first = count.first(window) or self.now
                wait = (first + span[window] - self.now).total_seconds()
                who = subject.split(":", 1)[1]
                return Throttled(
                    f"{who!r} reached its limit of {limit} {what} ({setting}); "
                    f"retry in {math.ceil(max(wait, 1))} s",
                    math.ceil(max(wait, 1)),
                )
        return self._cooldown(person, participant)

    def _cooldown(self, person: str, participant: str) -> Throttled | None:
        """Refusals in a row since the participant's last accepted version: the next
        submission waits cooldown · 2^(k−1) after the last of them."""
        in_a_row, last = 0, None
        for kind, at in reversed(self.recent[person]):
            if kind != REFUSAL:
                break
            in_a_row, last = in_a_row + 1, last or at
        if last is None:
            return None
        limits = self.limits
        cooldown = min(limits.cooldown_max_s, limits.cooldown_s * 2 ** (in_a_row - 1))
        wait = (last + timedelta(seconds=cooldown) - self.now).total_seconds()
        if wait <= 0:
            return None
        return Throttled(
            f"{participant!r} was refused by the screener {in_a_row} time(s) in a row: next "
            f"submission in {math.ceil(wait)} s (cooldown {cooldown:g} s, doubling per refusal; "
            "SRD_REFUSAL_COOLDOWN_S)",
            math.ceil(wait),
        )

    def record(self, *, participant: str, address: str | None, new: bool, accepted: bool) -> None:
        """Count a stored submission: its version or refusal, its registration."""
        person = participant_subject(participant)
        kind = VERSION if accepted else REFUSAL
        events = [(person, kind)]
        if address is not None:
            place = address_subject(address)
            events.append((place, kind))
            if new:
                events.append((place, REGISTRATION))
        for subject, event_kind in events:
            self.counts[(subject, event_kind)].pending.append(self.now)
            if subject == person:  # the cooldown reads a participant's own
                self.recent[subject].append((event_kind, self.now))
            self.rows.append({"subject": subject, "kind": event_kind, "created_at": self.now})

    def write(self, session: Session) -> None:
        """Insert the group's events (one multi-row insert)."""
        if self.rows:
            session.connection().execute(insert(RateEvent), self.rows)


def prune(session: Session, now: datetime) -> None:
    """Delete the events no limit counts any more."""
    session.execute(delete(RateEvent).where(RateEvent.created_at < now - KEEP))


def subjects(participants: list[str], addresses: list[str | None]) -> list[str]:
    """The subjects a group's limits read."""
    found = [participant_subject(p) for p in participants]
    found += [address_subject(a) for a in addresses if a is not None]
    return list(dict.fromkeys(found))


def _aware(value: datetime, like: datetime) -> datetime:
    """SQLite hands back naive UTC timestamps from aggregates; compare them as aware ones."""
    return value if value.tzinfo is not None else value.replace(tzinfo=like.tzinfo)
