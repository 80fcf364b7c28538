"""The states an auction, a job, a fine-tuning round and a round answer go through: the values
stored in their ``status``/``outcome`` columns and shown by the API, named once.

They are ``StrEnum``s: a member equals its string, so rows, JSON and queries take either.
"""

from __future__ import annotations

from enum import StrEnum


class AuctionStatus(StrEnum):
    """pending → running → finished, or failed, or cancelled (pending or running, by the
    operator)."""

    PENDING = "pending"
    RUNNING = "running"
    FINISHED = "finished"
    FAILED = "failed"
    CANCELLED = "cancelled"


AUCTION_UNFINISHED = (AuctionStatus.PENDING, AuctionStatus.RUNNING)
"""An auction in these states is still to be played (resumed after a restart)."""
AUCTION_ENDED = (AuctionStatus.FINISHED, AuctionStatus.FAILED, AuctionStatus.CANCELLED)


class JobStatus(StrEnum):
    """queued → running → succeeded, or failed, or cancelled (queued or running)."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


JOB_UNFINISHED = (JobStatus.QUEUED, JobStatus.RUNNING)
"""A job in these states can still be cancelled (and is run again after a restart)."""
JOB_ENDED = (JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELLED)


class RoundStatus(StrEnum):
    """A remote fine-tuning round: open until every asked patron answered or its deadline."""

    OPEN = "open"
    CLOSED = "closed"


class AnswerOutcome(StrEnum):
    """A patron's answer to a fine-tuning round."""

    PENDING = "pending"
    """The upload came in time and awaits its verdict (it counts as an answer)."""
    ACCEPTED = "accepted"
    """The upload passed the re-screening: it bids from the next iteration."""
    REFUSED = "refused"
    """The upload failed the re-screening: the previous version bids on."""
    HELD = "held"
    """The re-screening held the upload for an inspector: the previous version bids on."""
    LATE = "late"
    """The upload came after the round closed."""
    MISSING = "missing"
    """No upload before the round closed."""


ANSWERED = (
    AnswerOutcome.ACCEPTED,
    AnswerOutcome.REFUSED,
    AnswerOutcome.HELD,
    AnswerOutcome.PENDING,
)
"""Outcomes that count as an answer to the round (a late upload does not)."""
JUDGED = (AnswerOutcome.ACCEPTED, AnswerOutcome.REFUSED, AnswerOutcome.HELD)
"""Answers whose verdict is recorded."""


class ModelStatus(StrEnum):
    """A model version's verdict (``screener.review``): accepted enters auctions; refused never
    does (unless an appeal gets it admitted); held waits for an inspector's decision."""

    ACCEPTED = "accepted"
    REFUSED = "refused"
    HELD = "held"


class ReviewDecision(StrEnum):
    """An entry of a model's audit log: an inspector admits or refuses a held model; its
    participant appeals a refusal (once)."""

    ADMIT = "admit"
    REFUSE = "refuse"
    APPEAL = "appeal"
