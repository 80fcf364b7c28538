"""Quotas and rate limits on ``POST /submit``, counted in the database (``rate_events``), so
that every API process sharing the database enforces the same limits.

Per participant:
* new accepted versions per minute and per day (refused versions do not use them up);
* a cooldown after screener refusals, doubling with each refusal in a row (reset by an accepted
  version), so that nobody can probe the screener's thresholds quickly.

Per client address:
* registrations (first submissions of a new participant name) per day;
* new accepted versions per minute and per day, over all its participants;
* screener refusals per hour (a refused or held round upload counts too, and starts its
  participant's cooldown, which an accepted one ends: ``record_round_upload``);
* appeals per day (``appeal_throttle``: each puts a model back in the inspectors' queue).

A submission over a limit is answered 429 with ``Retry-After`` and a message naming the limit
and its setting; its verdict is not revealed and nothing of it is stored. ``Throttle`` reads a
submission's counts in the transaction that stores it (the statements: ``crud.quotas``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import Connection
from sqlalchemy.orm import Session

from server.api.connections import client_address
from server.config import Settings
from server.store import crud

VERSION, REGISTRATION, REFUSAL, APPEAL = "version", "registration", "refusal", "appeal"
ROUND_VERSION = "round"
"""A round upload the screener accepted: it ends its participant's refusals in a row, as an
accepted version does, and counts for no quota (a patron's uploads are the rounds')."""
MINUTE, HOUR, DAY = timedelta(minutes=1), timedelta(hours=1), timedelta(days=1)
KEEP = DAY + HOUR
"""Events older than this count for no limit and are pruned."""


_PERSON = "participant:"


def participant_subject(name: str) -> str:
    return f"{_PERSON}{name}"


def address_subject(host: str) -> str:
    return f"address:{client_address(host)}"


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


class Throttle:
    """The limits applied to one submission of ``participant`` from ``address``, read at
    ``now`` in the session's transaction (two queries)."""

    def __init__(
        self,
        session: Session,
        limits: Limits,
        now: datetime,
        *,
        participant: str,
        address: str | None,
    ) -> None:
        self.limits, self.now, self.participant = limits, now, participant
        self.person = participant_subject(participant)
        self.place = None if address is None else address_subject(address)
        subjects = [self.person] if self.place is None else [self.person, self.place]
        self.counts = crud.rate_counts(
            session,
            subjects=subjects,
            windows={"day": now - DAY, "hour": now - HOUR, "minute": now - MINUTE},
        )
        # The cooldown reads a participant's refusals in a row, never an address's: an address
        # shared by many participants would fetch all their versions of the last hour.
        self.recent = crud.recent_events(
            session,
            subject=self.person,
            kinds=(VERSION, REFUSAL, ROUND_VERSION),
            since=now - timedelta(seconds=limits.cooldown_max_s),
        )

    def check(self, *, new: bool) -> Throttled | None:
        """The first limit this submission (of a ``new`` participant, or not) would break, or
        None."""
        limits, person, place = self.limits, self.person, self.place
        checks: list[tuple[str, str, str, int, str, str]] = [
            (person, VERSION, "minute", limits.versions_per_minute, "versions per minute",
             "SRD_QUOTA_VERSIONS_PER_MINUTE"),
            (person, VERSION, "day", limits.versions_per_day, "versions per day",
             "SRD_QUOTA_VERSIONS_PER_DAY"),
        ]  # fmt: skip
        if place is not None:
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
        for subject, kind, window, limit, what, setting in checks:
            count = self.counts.get((subject, kind))
            over = _over(count, subject, window, limit, what, setting, self.now)
            if over is not None:
                return over
        return self._cooldown()

    def _cooldown(self) -> Throttled | None:
        """Refusals in a row since the participant's last accepted version: the next
        submission waits cooldown · 2^(k−1) after the last of them."""
        in_a_row, last = 0, None
        for kind, at in reversed(self.recent):
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
            f"{self.participant!r} was refused or held by the screener {in_a_row} time(s) in a "
            f"row: next submission in {math.ceil(wait)} s (cooldown {cooldown:g} s, doubling per "
            "refusal; "
            "SRD_REFUSAL_COOLDOWN_S)",
            math.ceil(wait),
        )

    def record(self, session: Session, *, new: bool, accepted: bool) -> None:
        """Count the submission as stored: its version or refusal, its registration."""
        kind = VERSION if accepted else REFUSAL
        events = [(self.person, kind)]
        if self.place is not None:
            events.append((self.place, kind))
            if new:
                events.append((self.place, REGISTRATION))
        crud.insert_rate_events(session, events=events, now=self.now)


def appeal_throttle(
    session: Session, *, address: str | None, per_day: int, now: datetime
) -> Throttled | None:
    """Whether an appeal from ``address`` would pass its ``per_day`` appeals
    (``SRD_QUOTA_ADDRESS_APPEALS_PER_DAY``); None when it may go on. A request without an
    address (in-process) is not counted."""
    if address is None:
        return None
    place = address_subject(address)
    crud.lock_subject(session, place)  # concurrent appeals count one another (PostgreSQL)
    windows = {"day": now - DAY, "hour": now - HOUR, "minute": now - MINUTE}
    count = crud.rate_counts(session, subjects=[place], windows=windows).get((place, APPEAL))
    what = "appeals per day from one address"
    return _over(count, place, "day", per_day, what, "SRD_QUOTA_ADDRESS_APPEALS_PER_DAY", now)


_SPAN = {"minute": MINUTE, "hour": HOUR, "day": DAY}


def _over(
    count: crud.RateCount | None,
    subject: str,
    window: str,
    limit: int,
    what: str,
    setting: str,
    now: datetime,
) -> Throttled | None:
    """The refusal of a request whose ``subject`` reached ``limit`` events of its kind in
    ``window`` (``what`` and ``setting`` name the limit), waiting until its oldest leaves the
    window; None under the limit."""
    if count is None or getattr(count, window) < limit:
        return None
    wait = math.ceil(max((count.oldest.get(window, now) + _SPAN[window] - now).total_seconds(), 1))
    who = subject.split(":", 1)[1]
    return Throttled(
        f"{who!r} reached its limit of {limit} {what} ({setting}); retry in {wait} s", wait
    )


def record_round_upload(
    connection: Connection,
    *,
    participant: str,
    address: str | None,
    accepted: bool,
    now: datetime,
) -> None:
    """Count a round upload's verdict as ``/submit`` counts its own: refused or held, a refusal
    of its participant and its address (it starts the participant's cooldown and spends the
    address's refusals per hour); accepted, the end of its participant's refusals in a row.
    A patron's one upload per round is not itself throttled: its deadline is judged at
    arrival, and the rounds are the operator's."""
    if accepted:
        events = [(participant_subject(participant), ROUND_VERSION)]
    else:
        events = [(participant_subject(participant), REFUSAL)]
        if address is not None:
            events.append((address_subject(address), REFUSAL))
    crud.insert_rate_events(connection, events=events, now=now)


def record_admitted(session: Session, *, participant: str, now: datetime) -> None:
    """Count a held version an inspector admitted as the participant's accepted version: it
    ends the refusals in a row that its hold began (the cooldown)."""
    crud.insert_rate_events(session, events=[(participant_subject(participant), VERSION)], now=now)


def record_appeal(session: Session, *, address: str | None, now: datetime) -> None:
    """Count an appeal against its address (in the transaction that stores it)."""
    if address is not None:
        crud.insert_rate_events(session, events=[(address_subject(address), APPEAL)], now=now)


def prune(session: Session, now: datetime) -> None:
    """Delete the events no limit counts any more."""
    crud.prune_rate_events(session, before=now - KEEP)
