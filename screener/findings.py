"""What a check found over a batch of manifests, and the plain words for the neurons.

Checks come in groups (``Checks``): K checks evaluated together over P manifests, one boolean
column per check. Screening a batch is then a few array operations per group, and messages are
written only for the manifests that failed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]

ROLE = {
    "PG": "the high-price neuron",
    "SZ": "the size neuron",
    "LSR": "the limited-supply-rush neuron",
    "ST": "the sub-type neuron",
    "B": "the buy neuron",
    "L": "the hold neuron",
    "Q": "the quit neuron",
    "PGL": "the judgement 'holding at a high price is right'",
    "BC": "the judgement 'buying cheap is right'",
    "FQ": "the judgement 'quitting a good fish is wrong'",
    "T": "the verdict 'right'",
    "F": "the verdict 'wrong'",
}
"""What each named neuron means, as the messages say it."""

INPUT_WORDS = {
    "price": "the price",
    "length": "the length",
    "weight": "the weight",
    "gill": "the gill colour",
    "st1": "sub-type flag st1",
    "st2": "sub-type flag st2",
    "st3": "sub-type flag st3",
    "buy_fraction": "the previous buy fraction",
}
"""The inputs in words."""


class Checks(NamedTuple):
    """K checks over P manifests: the rule and neuron of each, ``failed`` (P, K) (NaN
    comparisons count as passed), and ``message(k, p)``, the words for manifest p failing
    check k."""

    rules: tuple[str, ...]
    neurons: tuple[str, ...]
    failed: Mask
    message: Callable[[int, int], str]


def check(rule: str, neuron: str, failed: Mask, message: Callable[[int], str]) -> Checks:
    """A single check (``failed`` (P,)) as a group of one."""
    return Checks((rule,), (neuron,), failed[:, None], lambda k, p: message(p))


def fmt(value: float, spec: str = ".3g") -> str:
    """A number as a reason's words print it: with ``spec``, in the short ``g`` form from a
    million up (a weight of 1e308 is no 300-digit line), and an overflow said in words (the
    magnitude rule refuses such weights; the other rules still read them)."""
    value = float(value)
    if not math.isfinite(value):
        return "not finite (beyond the float range)"
    if abs(value) >= 1e6 and not spec.endswith("g"):
        return ("+" if spec.startswith("+") and value >= 0 else "") + f"{value:.3g}"
    return format(value, spec)


def fmt_price(value: float) -> str:
    """A price or price-like number as the messages print it."""
    return fmt(value, ".2f")


def fmt_scores(scores: Array) -> str:
    """Decision scores B, L, Q as the messages print them; when the two leading ones print
    alike, by how much the leader leads (the market decides by any margin)."""
    values = [float(v) for v in scores]
    shown = [fmt(v, "+.2f") for v in values]
    words = ", ".join(f"{name} {text}" for name, text in zip("BLQ", shown, strict=True))
    if not all(math.isfinite(v) for v in values):
        return words
    lead = max(range(3), key=values.__getitem__)  # the first of equals, as argmax picks
    runner = max((k for k in range(3) if k != lead), key=values.__getitem__)
    if shown[lead] == shown[runner]:
        gap = values[lead] - values[runner]
        first, second = "BLQ"[lead], "BLQ"[runner]
        words += (
            f", {first} leading {second} by {gap:.2g}"
            if gap > 0
            else f", {first} and {second} tied exactly (a tie goes to {first})"
        )
    return words
