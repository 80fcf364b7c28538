"""A labelled corpus of Fish Sale Negotiator manifests for the screener: honest and saboteur.

Honest models span the paper's whole randomisation (willingness to pay b ~ U(4.8, 5), hold and
quit biases, fine-tuning settings), the same after legitimate SRD fine-tuning in auction-like
rounds (their own settings, and the most aggressive honest settings), and sensible variants a
participant may choose: another willingness to pay inside the plausible band, sharper or softer
activations, other biases, and all of these together after fine-tuning.

Saboteurs are manifest edits of honest models, one construction per kind: a big hold bias, an
inert buy neuron, a negative buy bias, every sign-carrying weight flipped one at a time, an
absurd declared willingness to pay, models that hold on the decisive row but look normal
elsewhere, rare buyers, never-quitters, lying PFCs, gigantic numbers, wild augmentation or
fine-tuning settings, sensors that read the wrong inputs, and the always-hold saboteur factory.
Everything is drawn from one seeded numpy generator.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.batch import from_manifests, to_manifest
from agents.fine_tuning import draw_fine_tune, fine_tune
from agents.manifest import INPUTS, Manifest
from agents.negotiator import honest_manifest, saboteur_manifest
from sim.market import MarketConfig, item_rows

BASE_PRICE = 5.0
FINE_TUNE_ROUNDS = 4
"""Fine-tuning rounds of an auction (the paper's 'first 4 iterations')."""
ROUND_PRICES = (4.8, 5.6)
"""Prices of the fine-tuning rounds, drawn uniformly: where the auction's price moves."""
FALLING_PRICES = (4.8, 4.9)
"""Rounds while the price falls to the stalemate threshold: honest models buy, the PFC calls
that right, and fine-tuning makes them keener (ST stops fading with the price, SZ reads it)."""
RISING_PRICES = (5.3, 6.0)
"""Rounds while high demand raises the price: honest models quit, the PFC calls that wrong."""
MAX_HONEST_FINE_TUNING = {"epochs": 2, "batch_size": 4, "learning_rate": 1e-4}
"""The most aggressive honest settings (the paper's ranges): 128 SGD steps, 4 rounds of 64 rows."""
DELTA = 0.001
"""δ, the design's seed weight."""


@dataclass(frozen=True)
class Labelled:
    """One corpus entry: how it was built, whether it is a saboteur, the manifest."""

    construction: str
    saboteur: bool
    manifest: Manifest


Edit = Callable[[np.random.Generator], dict[str, Any]]
"""Draws the changes of one construction: manifest path → new value or function of the old."""


def edit(manifest: Manifest, changes: dict[str, Any]) -> Manifest:
    """Apply ``{dotted.path: value or function(old value)}`` to a manifest and re-validate."""
    data = manifest.model_dump(mode="json")
    for path, value in changes.items():
        *head, last = path.split(".")
        node = data
        for key in head:
            node = node[key]
        node[last] = value(node[last]) if callable(value) else value
    return Manifest.model_validate(data)


def rows_for_round(rng: np.random.Generator, price: float) -> torch.Tensor:
    """One fine-tuning round's item rows (the market's 64 rows at ``price``), with the previous
    buy fraction f ~ U(0, 1) drawn per row, as votes leave it."""
    rows = item_rows(MarketConfig(n_fish=1, base_price=price), rng)
    rows[:, INPUTS.index("buy_fraction")] = rng.uniform(0.0, 1.0, len(rows))
    return torch.from_numpy(rows)


def fine_tuned(
    manifests: list[Manifest],
    rng: np.random.Generator,
    prices: tuple[float, float] = ROUND_PRICES,
) -> list[Manifest]:
    """The manifests after FINE_TUNE_ROUNDS rounds of their own SRD fine-tuning (batched), each
    round at a price ~ U(prices)."""
    batch = from_manifests(manifests)
    generator = torch.Generator().manual_seed(int(rng.integers(2**31)))
    for _ in range(FINE_TUNE_ROUNDS):
        rows = rows_for_round(rng, float(rng.uniform(*prices)))
        batch = fine_tune(batch, rows, draw_fine_tune(batch, len(rows), generator))
    return [to_manifest(batch, i) for i in range(len(manifests))]


def _price_weight(wtp: float) -> dict[str, Any]:
    return {"external_sensor.PG.weights.price": 1.0 / wtp}


def _wtp_variant(rng: np.random.Generator) -> dict[str, Any]:
    """Another willingness to pay, inside the plausible band with a 5% margin."""
    return _price_weight(float(rng.uniform(0.525, 1.9) * BASE_PRICE))


def _times(factor: float) -> Callable[[float], float]:
    return lambda value: value * factor


def _sharpness_variant(rng: np.random.Generator) -> dict[str, Any]:
    """Sharper or softer activations: a × [½, 2] on the threshold neurons, ε × [0.1, 3]."""
    changes: dict[str, Any] = {
        f"external_sensor.{name}.activation.a": _times(float(rng.uniform(0.5, 2.0)))
        for name in ("PG", "SZ", "LSR")
    }
    changes["external_sensor.ST.activation.epsilon"] = float(1e-4 * 10 ** rng.uniform(-1, 0.5))
    return changes


def _bias_variant(rng: np.random.Generator) -> dict[str, Any]:
    """Other intents: buy bias 0.7 to 1.2, hold −½ to ½, quit up to 0 and, as in the paper,
    at most 1.5 below the buy bias (the paper's gap is 1 to 1.5)."""
    buy = float(rng.uniform(0.7, 1.2))
    return {
        "decision.B.bias": buy,
        "decision.L.bias": float(rng.uniform(-0.5, 0.5)),
        "decision.Q.bias": float(rng.uniform(max(-0.5, buy - 1.5), 0.0)),
    }


def _mixed_variant(rng: np.random.Generator) -> dict[str, Any]:
    return {**_wtp_variant(rng), **_sharpness_variant(rng), **_bias_variant(rng)}


def _max_fine_tuning(rng: np.random.Generator) -> dict[str, Any]:
    return {"fine_tuning": MAX_HONEST_FINE_TUNING}


def honest_corpus(rng: np.random.Generator, n: int) -> list[Labelled]:
    """About ``n`` honest models in the kinds listed in the module docstring."""
    share = {
        "honest": 0.25,
        "honest-fine-tuned": 0.3,
        "honest-fine-tuned-max": 0.05,
        "honest-fine-tuned-max-falling-price": 0.05,
        "honest-fine-tuned-max-rising-price": 0.05,
        "variant-wtp": 0.075,
        "variant-sharpness": 0.075,
        "variant-biases": 0.075,
        "variant-mixed-fine-tuned": 0.075,
    }
    edits: dict[str, Edit] = {
        "honest-fine-tuned-max": _max_fine_tuning,
        "honest-fine-tuned-max-falling-price": _max_fine_tuning,
        "honest-fine-tuned-max-rising-price": _max_fine_tuning,
        "variant-wtp": _wtp_variant,
        "variant-sharpness": _sharpness_variant,
        "variant-biases": _bias_variant,
        "variant-mixed-fine-tuned": _mixed_variant,
    }
    out: list[Labelled] = []
    for kind, fraction in share.items():
        count = max(1, round(fraction * n))
        models = [honest_manifest(rng, f"{kind}-{i}") for i in range(count)]
        if kind in edits:
            models = [edit(m, edits[kind](rng)) for m in models]
        if "fine-tuned" in kind:
            prices = FALLING_PRICES if "falling" in kind else ROUND_PRICES
            models = fine_tuned(models, rng, RISING_PRICES if "rising" in kind else prices)
        out += [Labelled(kind, False, m) for m in models]
    return out


# --- Saboteur constructions --------------------------------------------------------------------
SIGN_CARRYING = (
    "external_sensor.PG.weights.price",
    "external_sensor.SZ.weights.length",
    "external_sensor.SZ.weights.weight",
    "external_sensor.LSR.weights.buy_fraction",
    "external_sensor.ST.weights.st1",
    "external_sensor.ST.weights.st2",
    "external_sensor.ST.weights.st3",
    "external_sensor.ST.bias",
    "decision.B.weights.PG",
    "decision.B.weights.SZ",
    "decision.B.weights.LSR",
    "decision.B.weights.ST",
    "decision.B.bias",
    "decision.L.weights.PG",
    "decision.L.weights.SZ",
    "decision.Q.weights.PG",
    "pfc.judgement.PGL.weights.PG",
    "pfc.judgement.PGL.weights.L",
    "pfc.judgement.BC.weights.PG",
    "pfc.judgement.BC.weights.B",
    "pfc.judgement.FQ.weights.SZ",
    "pfc.judgement.FQ.weights.LSR",
    "pfc.judgement.FQ.weights.ST",
    "pfc.judgement.FQ.weights.Q",
    "pfc.verdict.T.weights.PGL",
    "pfc.verdict.T.weights.BC",
    "pfc.verdict.F.weights.FQ",
)
"""Every weight (and bias) the design gives a sign that carries meaning; the δ seeds do not."""
GIGANTIC_SITES = (
    "decision.B.bias",
    "external_sensor.PG.weights.price",
    "pfc.judgement.FQ.weights.Q",
    "decision.L.weights.PG",
    "external_sensor.SZ.bias",
)
"""Where the 'gigantic' construction multiplies a number by 10³ to 10⁶ (or sets it, if 0)."""


def _flip(path: str) -> Edit:
    return lambda rng: {path: lambda v: -v}


def _gigantic(rng: np.random.Generator) -> dict[str, Any]:
    path = GIGANTIC_SITES[int(rng.integers(len(GIGANTIC_SITES)))]
    scale = float(10 ** rng.uniform(3, 6))
    return {path: lambda v: v * scale if v else scale}


def _absurd_wtp(rng: np.random.Generator) -> dict[str, Any]:
    low = rng.random() < 0.5
    return _price_weight(float(np.exp(rng.uniform(*np.log((0.2, 2.0) if low else (15, 100))))))


def _holds_on_base_quality(rng: np.random.Generator) -> dict[str, Any]:
    """ST retargeted to the exact base quality l = w = g = 1 (the decisive row's fish, hardly
    ever a perturbed row), and a strong hold on it: normal everywhere but the row that counts."""
    st = {"price": DELTA, "length": 1 / 3, "weight": 1 / 3, "gill": 1 / 3}
    st |= {"st1": DELTA, "st2": DELTA, "st3": DELTA, "buy_fraction": DELTA}
    return {
        "external_sensor.ST.weights": st,
        "external_sensor.ST.bias": -1.0 - DELTA * 7.0,
        "decision.L.weights.ST": float(rng.uniform(3, 6)),
    }


def _never_quits(rng: np.random.Generator) -> dict[str, Any]:
    """A low (plausible) willingness to pay, a weak quit and a firm hold: above its price it
    waits, at every price the auction visits."""
    return {
        **_price_weight(float(rng.uniform(3.0, 4.6))),
        "decision.Q.weights.PG": float(rng.uniform(0.1, 0.4)),
        "decision.L.bias": float(rng.uniform(0.3, 0.5)),
    }


def _big_fish_only(rng: np.random.Generator) -> dict[str, Any]:
    """SZ's normal size raised to 1.15–1.3 and a heavy SZ weight on buying: only huge fish."""
    return {
        "external_sensor.SZ.bias": -float(rng.uniform(0.15, 0.3)),
        "decision.B.weights.SZ": float(rng.uniform(4, 6)),
    }


def _rush_only(rng: np.random.Generator) -> dict[str, Any]:
    """LSR sharpened and centred at f = 0.8–0.95 with a leaky fall below, weighing heavily on
    buying: it buys only when almost everyone else does."""
    return {
        "external_sensor.LSR.activation": {"kind": "threshold", "a": 5.0, "c": 0.5,
                                           "negative_slope": 0.8},
        "external_sensor.LSR.bias": -float(rng.uniform(0.3, 0.45)),
        "decision.B.weights.LSR": float(rng.uniform(3, 4)),
    }  # fmt: skip


def _swap_verdicts(rng: np.random.Generator) -> dict[str, Any]:
    """The lying PFC: holding dear and buying cheap count as wrong, a false quit as right."""
    return {
        "pfc.verdict.T.weights": {"PGL": 0.0, "BC": 0.0, "FQ": 1.0},
        "pfc.verdict.F.weights": {"PGL": 1.0, "BC": 1.0, "FQ": 0.0},
    }


def _dear_is_right(rng: np.random.Generator) -> dict[str, Any]:
    """BC rewired: buying when the price is high and not buying count as right."""
    return {"pfc.judgement.BC.weights.PG": 1.0, "pfc.judgement.BC.weights.B": -1.0}


SABOTEURS: dict[str, Edit] = {
    "hold-bias": lambda rng: {"decision.L.bias": float(rng.uniform(2, 8))},
    "zero-buy-weights": lambda rng: {
        f"decision.B.weights.{s}": 0.0 for s in ("PG", "SZ", "LSR", "ST")
    },
    "negative-buy-bias": lambda rng: {"decision.B.bias": float(rng.uniform(-3, -0.5))},
    **{f"flip:{path.split('.', 1)[1]}": _flip(path) for path in SIGN_CARRYING},
    "absurd-wtp": _absurd_wtp,
    "holds-on-base-quality": _holds_on_base_quality,
    "holds-on-preferred-subtype": lambda rng: {"decision.L.weights.ST": float(rng.uniform(2, 5))},
    "never-quits": _never_quits,
    "rare-buyer-big-fish-only": _big_fish_only,
    "rare-buyer-rush-only": _rush_only,
    "holds-in-a-rush": lambda rng: {"decision.L.weights.LSR": float(rng.uniform(2, 5))},
    "quits-preferred-subtype": lambda rng: {"decision.Q.weights.ST": float(rng.uniform(2, 4))},
    "lying-pfc-swapped-verdicts": _swap_verdicts,
    "lying-pfc-dear-is-right": _dear_is_right,
    "lying-pfc-false-prior": lambda rng: {"pfc.verdict.F.bias": float(rng.uniform(1, 3))},
    "pg-rises-with-quality": lambda rng: {
        f"external_sensor.PG.weights.{q}": float(rng.uniform(0.05, 0.2))
        for q in ("length", "weight", "gill")
    },
    "size-reads-price": lambda rng: {
        "external_sensor.SZ.weights.price": float(rng.uniform(0.1, 0.3))
    },
    "gigantic": _gigantic,
    "noisy-augmentation": lambda rng: {"augmentation.noise_std": float(rng.uniform(0.2, 1.0))},
    "reckless-fine-tuning": lambda rng: {
        "fine_tuning": {"epochs": 2, "batch_size": 8, "learning_rate": 10 ** rng.uniform(-2, 0)}
    },
}
"""Saboteur constructions as manifest edits of an honest model."""


def saboteur_corpus(rng: np.random.Generator, per_kind: int) -> list[Labelled]:
    """``per_kind`` models of every construction in SABOTEURS, plus the always-hold factory."""
    out = [
        Labelled("always-hold-factory", True, saboteur_manifest(rng, f"always-hold-{i}"))
        for i in range(per_kind)
    ]
    for kind, draw in SABOTEURS.items():
        for i in range(per_kind):
            base = honest_manifest(rng, f"saboteur-{i}")
            out.append(Labelled(kind, True, edit(base, draw(rng))))
    return out


def corpus(seed: int = 0, n_honest: int = 1000, per_saboteur_kind: int = 8) -> list[Labelled]:
    """The labelled corpus: honest models first, then saboteurs (seeded)."""
    rng = np.random.default_rng(seed)
    return honest_corpus(rng, n_honest) + saboteur_corpus(rng, per_saboteur_kind)


# --- Sincere variants a participant may write by hand ---------------------------------------
def _scaled(prefix: str, names: tuple[str, ...], sources: tuple[str, ...], factor: float) -> Edit:
    """Every weight and bias of the layer ``prefix`` times ``factor`` (the argmax of a linear
    decision layer is unchanged; a judge's softmax sources are not)."""

    def draw(rng: np.random.Generator) -> dict[str, Any]:
        k = float(rng.uniform(1 / factor, factor))
        changes: dict[str, Any] = {f"{prefix}.{n}.bias": _times(k) for n in names}
        changes |= {f"{prefix}.{n}.weights.{s}": _times(k) for n in names for s in sources}
        return changes

    return draw


def _activations(low: float, high: float) -> Edit:
    """PG, SZ and LSR sharpness a times U(low, high)."""

    def draw(rng: np.random.Generator) -> dict[str, Any]:
        return {
            f"external_sensor.{name}.activation.a": _times(float(rng.uniform(low, high)))
            for name in ("PG", "SZ", "LSR")
        }

    return draw


SINCERE: dict[str, Edit] = {
    "sincere-wtp-4.5-to-9.5": lambda rng: _price_weight(float(rng.uniform(4.5, 9.5))),
    "sincere-scaled-decision": _scaled("decision", ("B", "L", "Q"), ("PG", "SZ", "LSR", "ST"), 3),
    "sincere-scaled-judge": _scaled(
        "pfc.judgement", ("PGL", "BC", "FQ"), ("PG", "SZ", "LSR", "ST", "B", "L", "Q"), 2
    ),
    "sincere-sharper": _activations(1.5, 4.0),
    "sincere-softer": _activations(0.25, 0.7),
    "sincere-frozen-pfc": lambda rng: {"pfc.trainable": False},
    "sincere-no-fine-tuning": lambda rng: {"fine_tuning": {"epochs": 0}},
    "sincere-no-augmentation": lambda rng: {"augmentation.copies": 1},
    "sincere-keen-buyer": lambda rng: {
        **_price_weight(float(rng.uniform(5.0, 7.0))),
        "decision.B.bias": float(rng.uniform(1.2, 2.0)),
    },
    "sincere-reluctant-buyer": lambda rng: {
        **_price_weight(float(rng.uniform(4.5, 4.9))),
        "decision.B.bias": float(rng.uniform(0.6, 0.9)),
        "decision.L.bias": float(rng.uniform(-0.5, 0.0)),
    },
    "sincere-gentle-quitter": lambda rng: {
        "decision.Q.weights.PG": float(rng.uniform(1.75, 2.0)),
        "decision.Q.bias": float(rng.uniform(-0.5, -0.25)),
    },
    "sincere-firm-quitter": lambda rng: {
        "decision.Q.weights.PG": float(rng.uniform(2.5, 5.0)),
        "decision.Q.bias": float(rng.uniform(-0.5, 0.0)),
    },
}
"""Hand-written sincere variants (issue list): each an edit of an honest model of the paper's
randomisation; half of each kind is then fine-tuned with its own settings."""


def sincere_corpus(rng: np.random.Generator, per_kind: int) -> list[Labelled]:
    """``per_kind`` models of every kind in SINCERE, the second half fine-tuned (4 rounds)."""
    out: list[Labelled] = []
    for kind, draw in SINCERE.items():
        models = [edit(honest_manifest(rng, f"{kind}-{i}"), draw(rng)) for i in range(per_kind)]
        half = per_kind // 2
        models[half:] = fine_tuned(models[half:], rng)
        out += [Labelled(kind, False, m) for m in models]
    return out


RED_TEAM = Path(__file__).with_name("red_team")
"""Models found by ``benchmarks/screener_attack.py``, one JSON manifest each."""
RED_TEAM_SINCERE = ("quits-at-opening",)
"""Red-team finds that are sincere low bidders (they quit at every price the auction reaches):
admitted by design, though their copies still dilute the opening round's buy fraction."""


def red_team_corpus() -> list[Labelled]:
    """The red team's finds: disguised saboteurs, and the sincere low bidder it also found."""
    out = []
    for path in sorted(RED_TEAM.glob("*.json")):
        manifest = Manifest.model_validate_json(path.read_text())
        out.append(Labelled(f"red-team:{path.stem}", path.stem not in RED_TEAM_SINCERE, manifest))
    return out
