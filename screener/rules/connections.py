"""The meaning of a layer's connections, read as signs, and the rule that checks a layer's
weights against it.

A layer's meaning (the paper's design) gives per listed connection (target, source): the sign its
weight must have, whether the meaning relies on it (then it must also carry at least
MIN_DESIGNED_WEIGHT) or it is only forbidden from pointing the wrong way (then it may drift by
SIGN_TOLERANCE), and what the model does if the sign is wrong.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import numpy.typing as npt

from screener import limits
from screener.findings import ROLE, Array, Checks

Meaning = dict[tuple[str, str], tuple[int, bool, str]]
"""(target, source) → (sign, relied upon, what a wrong sign makes the model do)."""


@dataclasses.dataclass(frozen=True)
class Layer:
    """A layer's meaning as arrays: per (target, source) the sign its weight must have and the
    floor of weight × sign (MIN_DESIGNED_WEIGHT where the meaning relies on the connection,
    −SIGN_TOLERANCE where it only forbids the wrong sign); the listed connections
    (``rows``, ``cols``, in the order of the meaning) and the unlisted ones."""

    targets: tuple[str, ...]
    sources: tuple[str, ...]
    meanings: tuple[tuple[int, bool, str], ...]
    sign: Array
    floor: Array
    rows: npt.NDArray[np.intp]
    cols: npt.NDArray[np.intp]
    stray_rows: npt.NDArray[np.intp]
    stray_cols: npt.NDArray[np.intp]


def layer_of(targets: tuple[str, ...], sources: tuple[str, ...], meaning: Meaning) -> Layer:
    """The ``Layer`` of a layer's ``meaning``, its neurons ``targets`` reading ``sources``."""
    sign = np.zeros((len(targets), len(sources)))
    floor = np.zeros_like(sign)
    for (t, s), (wanted, relied, _) in meaning.items():
        i, j = targets.index(t), sources.index(s)
        sign[i, j] = wanted
        floor[i, j] = limits.MIN_DESIGNED_WEIGHT if relied else -limits.SIGN_TOLERANCE
    rows = np.array([targets.index(t) for t, _ in meaning], dtype=np.intp)
    cols = np.array([sources.index(s) for _, s in meaning], dtype=np.intp)
    stray_rows, stray_cols = np.nonzero(sign == 0)
    return Layer(
        targets, sources, tuple(meaning.values()), sign, floor, rows, cols, stray_rows, stray_cols
    )


def _weights_phrase(target: str, source: str, weight: float) -> str:
    return f"{ROLE[target]} {target} has weight {weight:+.3g} from {source}, {ROLE[source]}"


def _sign_message(target: str, source: str, w: float, meaning: tuple[int, bool, str]) -> str:
    sign, _, consequence = meaning
    if w == 0:
        return (
            f"{ROLE[target]} {target} has no weight from {source}, {ROLE[source]}: the "
            "connection its meaning relies on is cut"
        )
    if sign * w > 0:
        return (
            f"{_weights_phrase(target, source, w)}: too weak to carry its meaning (at least "
            f"{limits.MIN_DESIGNED_WEIGHT:g} in size, sign {'+' if sign > 0 else '−'})"
        )
    return f"{_weights_phrase(target, source, w)}: this model {consequence}"


def connection_checks(
    rule: str, weights: Array, layer: Layer, stray_rule: str | None = None
) -> list[Checks]:
    """Every connection of a layer (weights (P, targets, sources)) against its meaning: a wrong
    sign beyond SIGN_TOLERANCE, a relied-upon weight below MIN_DESIGNED_WEIGHT, and (with
    ``stray_rule``) a connection the meaning does not list above PFC_OFF_DESIGN_LIMIT."""
    targets, sources, rows, cols = layer.targets, layer.sources, layer.rows, layer.cols
    wrong = (weights * layer.sign < layer.floor)[:, rows, cols]

    def sign_message(k: int, p: int) -> str:
        i, j = rows[k], cols[k]
        return _sign_message(targets[i], sources[j], float(weights[p, i, j]), layer.meanings[k])

    found = [Checks((rule,) * len(rows), tuple(targets[i] for i in rows), wrong, sign_message)]
    if stray_rule is not None:
        s_rows, s_cols = layer.stray_rows, layer.stray_cols
        stray = np.abs(weights[:, s_rows, s_cols]) > limits.PFC_OFF_DESIGN_LIMIT

        def stray_message(k: int, p: int) -> str:
            i, j = s_rows[k], s_cols[k]
            return (
                f"{_weights_phrase(targets[i], sources[j], weights[p, i, j])}: it is not about "
                f"{sources[j]} (at most {limits.PFC_OFF_DESIGN_LIMIT:g} in size)"
            )

        neurons = tuple(targets[i] for i in s_rows)
        found.append(Checks((stray_rule,) * len(s_rows), neurons, stray, stray_message))
    return found
