"""Disguised saboteurs: families of allowed-sign, in-band wirings built to hold at every price
the auction visits. Each ``Family`` has fixed edits and numbers (``Param``) a red team may tune;
``benchmarks/screener_attack.py`` searches them for the most harmful model the screener admits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.manifest import Manifest
from tests.support.corpus import edit


@dataclass(frozen=True)
class Param:
    """One number of a family: the manifest path and its range (``log``: drawn log-uniformly;
    ``inverse``: the path takes 1/value, e.g. a willingness to pay as PG's price weight)."""

    path: str
    low: float
    high: float
    log: bool = False
    inverse: bool = False
    integer: bool = False

    def value(self, u: float) -> float | int:
        """The number at position u ∈ [0, 1] of the range."""
        if self.log:
            v = float(np.exp(np.log(self.low) + u * (np.log(self.high) - np.log(self.low))))
        else:
            v = self.low + u * (self.high - self.low)
        if self.integer:
            return round(v)
        return 1.0 / v if self.inverse else v


@dataclass(frozen=True)
class Family:
    """A saboteur family: fixed edits plus numbers a red team may tune (``Param``)."""

    name: str
    params: tuple[Param, ...]
    fixed: tuple[tuple[str, Any], ...] = ()

    def build(self, base: Manifest, u: np.ndarray) -> Manifest:
        """``base`` with the fixed edits and the numbers at positions ``u`` (clipped to [0, 1])."""
        changes: dict[str, Any] = dict(self.fixed)
        for param, x in zip(self.params, np.clip(u, 0.0, 1.0), strict=True):
            changes[param.path] = param.value(float(x))
        return edit(base, changes)

    def draw(self, base: Manifest, rng: np.random.Generator) -> Manifest:
        return self.build(base, rng.random(len(self.params)))


_PG = "external_sensor.PG"
_SZ = "external_sensor.SZ"
_LSR = "external_sensor.LSR"
_ST = "external_sensor.ST"
_INTENTS = (
    Param("decision.B.bias", 0.5, 3.0),
    Param("decision.L.bias", -2.0, 1.0),
    Param("decision.Q.bias", -10.0, 0.0),
)
"""The FC biases every family may tune (the buy-intent rule wants B's above L's and Q's)."""


def _glances(judgement: str, sources: tuple[str, ...]) -> tuple[Param, ...]:
    """A judgement's weights from sources it is not about, within the rules' ±0.25."""
    return tuple(Param(f"pfc.judgement.{judgement}.weights.{s}", -0.25, 0.25) for s in sources)


DISGUISED = (
    # Declared willingness to pay inside the band but below the market; hold (not quit)
    # between it and a quit price just above the decisive window.
    Family(
        "low-price-holder",
        (
            Param(f"{_PG}.weights.price", 2.6, 4.75, inverse=True),
            Param(f"{_PG}.activation.a", 2.0, 200.0, log=True),
            Param(f"{_PG}.activation.negative_slope", 0.0, 1.0),
            Param("decision.L.weights.PG", 0.1, 10.0),
            Param("decision.Q.weights.PG", 0.1, 10.0),
            *_INTENTS,
        ),
    ),
    # SZ centred near the top of the size band with the steepest allowed slope: every fish on
    # sale reads "small"; large weights of allowed sign (L ← SZ, Q ← SZ negative) add a hold
    # push, a steep buy ← −PG below the price keeps the cheap fish bought.
    Family(
        "blind-size-holder",
        (
            Param(f"{_SZ}.bias", -0.55, -0.2),
            Param(f"{_SZ}.activation.a", 5.0, 50.0, log=True),
            Param(f"{_SZ}.activation.negative_slope", 0.3, 1.0),
            Param("decision.B.weights.SZ", 0.1, 2.0),
            Param("decision.L.weights.SZ", -10.0, -1.0),
            Param("decision.Q.weights.SZ", -10.0, 0.0),
            Param("decision.B.weights.PG", -10.0, -1.0),
            Param(f"{_PG}.activation.negative_slope", 0.01, 1.0),
            Param("decision.Q.weights.PG", 0.5, 10.0),
            *_INTENTS,
        ),
    ),
    # ST's bias nudged so that the base fish is not "its sub-type" (its buy push is gone), with
    # the blind size detector's hold push.
    Family(
        "blind-subtype-holder",
        (
            Param(f"{_ST}.bias", -0.6, -0.4),
            Param(f"{_ST}.activation.epsilon", 1e-6, 1e-2, log=True),
            Param("decision.B.weights.ST", 0.1, 3.0),
            Param(f"{_SZ}.bias", -0.55, -0.2),
            Param(f"{_SZ}.activation.negative_slope", 0.3, 1.0),
            Param("decision.L.weights.SZ", -10.0, 0.0),
            Param("decision.B.weights.PG", -10.0, -1.0),
            Param(f"{_PG}.activation.negative_slope", 0.01, 1.0),
            Param("decision.Q.weights.PG", 0.5, 10.0),
            *_INTENTS,
        ),
        ((f"{_SZ}.activation.a", 50.0),),
    ),
    # Rush-gated holding: LSR centred near f = 0.95 reads −1 at every ordinary buy fraction;
    # L ← LSR and Q ← LSR strongly negative (an allowed sign) hold unless everyone else rushes.
    Family(
        "rush-gated-holder",
        (
            Param(f"{_LSR}.bias", -0.5, -0.35),
            Param(f"{_LSR}.activation.a", 1.0, 10.0, log=True),
            Param(f"{_LSR}.activation.negative_slope", 0.3, 1.0),
            Param("decision.L.weights.LSR", -10.0, -1.0),
            Param("decision.Q.weights.LSR", -10.0, 0.0),
            Param("decision.B.weights.LSR", 0.1, 5.0),
            Param("decision.B.weights.PG", -10.0, -1.0),
            Param(f"{_PG}.activation.negative_slope", 0.01, 1.0),
            Param("decision.Q.weights.PG", 0.5, 10.0),
            *_INTENTS,
        ),
    ),
    # Fine-tuning drift: honest sensor and decision, a PFC whose judgement (within the rules'
    # limits) makes SRD fine-tuning at the legal maxima drift the model into holding.
    Family(
        "drifting-judge",
        (
            *_glances("PGL", ("SZ", "LSR", "ST", "B", "Q")),
            Param("pfc.judgement.PGL.weights.PG", 0.1, 10.0),
            Param("pfc.judgement.PGL.weights.L", 0.1, 10.0),
            *_glances("BC", ("SZ", "LSR", "ST", "L", "Q")),
            Param("pfc.judgement.BC.weights.PG", -10.0, -0.1),
            Param("pfc.judgement.BC.weights.B", 0.1, 10.0),
            *_glances("FQ", ("PG", "B", "L")),
            *(Param(f"pfc.judgement.{j}.bias", -0.25, 0.25) for j in ("PGL", "BC", "FQ")),
            Param("pfc.verdict.T.weights.PGL", 0.1, 10.0),
            Param("pfc.verdict.T.weights.BC", 0.1, 10.0),
            Param("pfc.verdict.F.weights.FQ", 0.1, 10.0),
            Param("pfc.verdict.F.bias", -0.2, 0.3),
            Param("fine_tuning.learning_rate", 1e-4, 1e-3, log=True),
            Param("fine_tuning.batch_size", 1, 8, integer=True),
        ),
        (("fine_tuning.epochs", 4),),
    ),
)  # fmt: skip
"""The disguised families: wired with allowed signs and in-band numbers, built to hold at every
price the auction visits (issue kinds; the red team tunes their numbers)."""
