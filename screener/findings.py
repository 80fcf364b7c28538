"""A finding of one check over a batch of manifests, and the plain words for the neurons."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

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


@dataclass(frozen=True)
class Finding:
    """One check over P manifests: which failed it, and the message for a failed one."""

    rule: str
    neuron: str
    failed: Mask
    message: Callable[[int], str]


def finding(rule: str, neuron: str, failed: Mask, message: Callable[[int], str]) -> Finding:
    """A Finding with ``failed`` as a plain boolean array (NaN comparisons count as passed)."""
    return Finding(rule, neuron, np.asarray(failed, dtype=np.bool_), message)


def fmt_price(value: float) -> str:
    """A price or price-like number as the messages print it."""
    return f"{value:.2f}"
