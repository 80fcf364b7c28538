"""What the screener says about a manifest: accepted or not, why in plain words, and the numbers
each bar it was held to measured; ``review``, which turns a verdict into accepted, refused or
held for a person to look at; and ``with_hold_reasons``, which says why a held model that the
screener accepted is held."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

PRICE = "price"
"""The units of the impact test's bar and of every other bar measured in price (the review
margin is in these units)."""

Review = Literal["accepted", "refused", "held"]

INSPECTED = ("keen-far-too-expensive", "rush-far-too-expensive", "buys-far-below-floor")
"""Bars that hold a model for an inspector when missed, whatever the margin (above 0), instead
of refusing it: the screener accepts the model, a server holds it. Their ``detail`` names the
neuron (``neuron``) and, when missed, says what the model does in words (``finding``)."""


@dataclass(frozen=True)
class Reason:
    """One finding: which rule, about which neuron (e.g. ``"B"`` or ``"PG"``), in plain words."""

    rule: str
    neuron: str
    message: str

    def to_dict(self) -> dict[str, str]:
        """JSON form ``{rule, neuron, message}``."""
        return asdict(self)


@dataclass(frozen=True)
class Evidence:
    """One bar a model was held to: the ``test`` (a rule name), what was measured and the bar
    in ``units``; ``passed`` when ``measured`` lies on the allowed side (``at least``: ≥ the bar,
    ``at most``: ≤). ``measured`` is None when there is nothing to measure a distance by (a hold
    with no purchase below it at all; a fine-tuned version refused by a rule without a bar in
    price, whose bar is None too). ``detail`` holds what explains the number: the
    references of the impact test, the decisive row's decisions with and without noise."""

    test: str
    measured: float | None
    bar: float | None
    units: str
    side: Literal["at least", "at most"]
    passed: bool
    detail: dict[str, Any] = field(default_factory=dict)

    def within(self, margin: float) -> bool:
        """Whether the measurement is in price and lies strictly within ``margin`` of the bar."""
        if self.units != PRICE or self.measured is None or self.bar is None:
            return False
        return abs(self.measured - self.bar) < margin

    def inspected(self) -> bool:
        """Whether this is a missed bar that holds the model for an inspector (``INSPECTED``)."""
        return not self.passed and self.test in INSPECTED

    def to_dict(self) -> dict[str, Any]:
        """JSON form ``{test, measured, bar, units, side, passed, detail}``: a number that is
        not finite (a sum overflowed: weights near the float's limit, which ``magnitude``
        refuses) is null, as JSON has no infinity."""
        finite: dict[str, Any] = _finite(asdict(self))
        return finite


def _finite(value: Any) -> Any:
    """``value`` with every float that is not finite, however deep, made None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value


@dataclass(frozen=True)
class Verdict:
    """The screener's decision on one manifest."""

    accepted: bool
    reasons: list[Reason] = field(default_factory=list)
    evidence: list[Evidence] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON form ``{accepted, reasons: [{rule, neuron, message}], evidence: [...]}``."""
        return {
            "accepted": self.accepted,
            "reasons": [r.to_dict() for r in self.reasons],
            "evidence": [e.to_dict() for e in self.evidence],
        }


def review(verdict: Verdict, margin: float) -> Review:
    """``accepted``, ``refused`` or ``held`` (for a person to decide) with a margin in price.

    Held when the decisive evidence lies within ``margin`` of its bar: an accepted model whose
    price-measured bar passed by less than the margin, or a refused one every one of whose
    reasons is a price-measured bar it missed by less than the margin (a refusal by a rule with
    no such measurement, or by more, stands). An accepted model that missed a bar of
    ``INSPECTED`` is held too, by any margin above 0. Margin 0 never holds.
    """
    if margin < 0:
        raise ValueError(f"margin must be ≥ 0, got {margin}")
    if verdict.accepted:
        held = any(e.within(margin) or (margin > 0 and e.inspected()) for e in verdict.evidence)
        return "held" if held else "accepted"
    if not verdict.reasons:
        return "refused"
    missed = [e for e in verdict.evidence if not e.passed]
    for reason in verdict.reasons:
        own = [e for e in missed if e.test == reason.rule]
        if not own or not all(e.within(margin) for e in own):
            return "refused"
    return "held"


def with_hold_reasons(verdict: Verdict, margin: float) -> Verdict:
    """The verdict with the reasons that hold an accepted model for a person, when it is held:
    one named after the bar (its neuron from the evidence's ``detail``) for each ``INSPECTED``
    bar it missed, in the evidence's own words, and a ``review-margin`` reason (neuron L: every
    other bar in price is about where the model holds) for each bar in price it passed by less
    than ``margin``; any other verdict unchanged."""
    if not verdict.accepted or review(verdict, margin) != "held":
        return verdict
    reasons = [
        Reason(
            e.test,
            str(e.detail.get("neuron", "B")),
            f"held for an inspector: {e.detail.get('finding', e.test)}",
        )
        for e in verdict.evidence
        if e.inspected()
    ]
    reasons += [
        Reason("review-margin", "L", _near_words(e.test, e.measured, e.bar, e.side, margin))
        for e in verdict.evidence
        if e.within(margin) and e.measured is not None and e.bar is not None
    ]
    return Verdict(verdict.accepted, [*verdict.reasons, *reasons], verdict.evidence)


def _near_words(test: str, measured: float, bar: float, side: str, margin: float) -> str:
    """Why a bar passed by less than ``margin`` holds the model, its numbers printed apart
    (4 decimals, more where those would print the two alike)."""
    digits = 4
    while digits < 8 and f"{measured:.{digits}f}" == f"{bar:.{digits}f}":
        digits += 1
    return (
        f"held for an inspector: {test} measured {measured:.{digits}f} against its bar "
        f"{bar:.{digits}f} ({side} the bar), passed by {abs(measured - bar):.{digits}f}, "
        f"within {margin:g} of its bar: too near to decide without a person"
    )
