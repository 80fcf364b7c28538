"""The noise-gated holder family: models whose decisions flip under their own augmentation
noise, so the clean probes see a sincere bidder and the market a holder.

ST reads length, weight and gill off-design (each weight k, within the off-design rule's
limit) and is re-centred on the base fish, with a selective peak √ε far narrower than the
jitter σ·k·√3 its own copies put on its pre-activation: clean, ST reads 1 on the base fish; on
the market's noisy copies only copy 0 (clean) finds the peak, so ST averages about 1/D. B leans
on ST (weight s), and the biases are solved so that, at buy fraction ½:

* clean (ST = 1), B leads until the price ``clean_to``, where Q overtakes it: a sincere bidder
  that quits above its price and never holds;
* on the noisy copies (ST ≈ 1/D), L overtakes B at ``hold_from`` and Q overtakes L at
  ``hold_to``: the market sees a model that holds over the decisive prices and buys only below.

With PG = tanh(20·(p/b − 1)) (b the declared willingness to pay) and x0, y1, x1 its values at
``hold_from``, ``hold_to``, ``clean_to``: B = 1 + b_B − PG + s·ST, L = 0.8·PG + b_L,
Q = 2·PG − ½ + b_Q give s = (3·x1 − 1.8·x0 − 1.2·y1) / (1 − 1/D), b_Q = b_B + s − 3·x1 + 1.5
and b_L = b_Q + 1.2·y1 − 0.5.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from tests.support.corpus import edit


@dataclass(frozen=True)
class NoiseGated:
    """The numbers of one noise-gated holder."""

    hold_from: float
    hold_to: float
    clean_to: float
    willingness: float = 4.8
    k: float = 1.0
    epsilon: float = 1e-6
    copies: int = 5
    sigma: float = 0.01
    buy_bias: float = 0.0
    seed: int = 0

    def build(self, name: str) -> Manifest:
        def pg(price: float) -> float:
            return float(np.tanh(20.0 * (price / self.willingness - 1.0)))

        x0, y1, x1 = pg(self.hold_from), pg(self.hold_to), pg(self.clean_to)
        s = (3 * x1 - 1.8 * x0 - 1.2 * y1) / (1 - 1 / self.copies)
        b_q = self.buy_bias + s - 3 * x1 + 1.5
        b_l = b_q + 1.2 * y1 - 0.5
        honest = honest_manifest(np.random.default_rng(self.seed), name, fine_tune=False)
        st = "external_sensor.ST"
        return edit(
            honest,
            {
                "description": (
                    f"Red team (noise-gated holder): clean it buys up to {self.clean_to:.2f} "
                    f"and quits; on its noisy copies it holds from {self.hold_from:.2f} to "
                    f"{self.hold_to:.2f}."
                ),
                f"{st}.weights.length": self.k,
                f"{st}.weights.weight": self.k,
                f"{st}.weights.gill": self.k,
                f"{st}.weights.price": 0.0,
                f"{st}.weights.buy_fraction": 0.0,
                f"{st}.bias": -0.5 - 3 * self.k,
                f"{st}.activation.epsilon": self.epsilon,
                "external_sensor.PG.weights.price": 1 / self.willingness,
                "decision.B.weights.ST": s,
                "decision.B.bias": 1.0 + self.buy_bias,
                "decision.L.bias": b_l,
                "decision.Q.bias": -0.5 + b_q,
                "augmentation.copies": self.copies,
                "augmentation.noise_std": self.sigma,
            },
        )


NOISE_GATED = {
    "noise-gated-holder-a": NoiseGated(4.85, 5.15, 5.15, seed=1),
    "noise-gated-holder-b": NoiseGated(4.88, 5.10, 5.24, k=2.0, seed=2),
    "noise-gated-holder-c": NoiseGated(4.85, 5.05, 5.08, k=0.8, epsilon=1e-5, seed=3),
    "noise-gated-holder-d": NoiseGated(4.90, 5.00, 5.12, copies=8, seed=4),
    "noise-gated-holder-e": NoiseGated(4.86, 5.12, 5.20, sigma=0.02, copies=4, seed=5),
    "noise-gated-holder-f": NoiseGated(4.85, 5.02, 5.10, k=2.5, buy_bias=0.3, seed=6),
}
"""The family's variants: hold bands 4.85-5.15 down to 4.90-5.00, clean prices 5.08-5.24, ST's
off-design weight 0.8-2.5, ε 1e-6-1e-5, 4-8 copies, σ 0.01-0.02, other honest draws."""


def noise_gated_holders() -> dict[str, Manifest]:
    """Every variant, built (as `tests/support/red_team/noise-gated-holder-*.json` holds them)."""
    return {name: numbers.build(f"red-team-{name}") for name, numbers in NOISE_GATED.items()}


@dataclass(frozen=True)
class NoiseGatedFamily:
    """The family as a red team tunes it (``benchmarks/screener_attack.py``): positions
    u ∈ [0, 1]⁸ map to hold band, clean price, ST's off-design weight and ε, copies, σ and the
    buy bias, the way ``tests.support.disguised.Family`` maps its numbers."""

    name: str = "noise-gated-holder"
    params: tuple[str, ...] = (
        "hold_from",
        "hold_to",
        "clean_to",
        "k",
        "epsilon",
        "copies",
        "sigma",
        "buy_bias",
    )

    def numbers(self, u: np.ndarray) -> NoiseGated:
        u = np.clip(u, 0.0, 1.0)
        hold_from = 4.82 + 0.13 * float(u[0])
        return NoiseGated(
            hold_from=hold_from,
            hold_to=hold_from + 0.03 + 0.25 * float(u[1]),
            clean_to=5.02 + 0.25 * float(u[2]),
            k=0.5 + 2.0 * float(u[3]),
            epsilon=float(10 ** (-6 + 2 * u[4])),
            copies=2 + round(14 * float(u[5])),
            sigma=0.005 + 0.045 * float(u[6]),
            buy_bias=0.5 * float(u[7]),
        )

    def build(self, base: Manifest, u: np.ndarray) -> Manifest:
        """The model at positions u (``base`` names it; the honest draw is the family's)."""
        return self.numbers(u).build(base.participant)
