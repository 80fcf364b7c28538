"""The Fish Sale Negotiator's design (paper, "The Server and Fish Sale Negotiator"): every
designed number with its meaning, in one place, and the patron factories built from it.

An FSN reads one item row x = (p, l, w, g, st1, st2, st3, f) and decides buy, hold or quit:

* implicit contrastive augmentation: D_ic copies of x (copy 0 clean, the others jittered by
  N(0, σ²) on every channel except the sub-types); only the plain rows travel, the model makes
  its own noisy copies.
* external sensor ES, one linear map of the 8 inputs then an activation per neuron:
  PG (price too high for me), SZ (big fish), LSR (limited supply rush: others are buying),
  ST (my preferred sub-type).
* decision FC: B (buy), L (hold, want a lower price), Q (quit), linear in ES, averaged over the
  copies; the decision is the argmax (ties → the lowest index, i.e. buy before hold before quit).
* prefrontal cortex PFC, the self-judge: softmax of [PG, SZ, LSR, ST, B, L, Q] → judgements PGL
  (holding at a high price), BC (buying cheap), FQ (false quit) → tanh → verdicts T (right) and
  F (wrong), averaged over the copies. SRD fine-tuning minimises CEL([T, F], argmax [T, F]) with
  plain SGD.

The rest of the model lives beside this module: ``agents.batch`` (P negotiators stacked in one
``FSNBatch``, and its exact manifest round trip), ``agents.forward`` (the forward pass over
patrons × rows × copies) and ``agents.fine_tuning`` (SRD fine-tuning, batched over patrons).
"""

from __future__ import annotations

import functools

import numpy as np
from pydantic import TypeAdapter

from agents.manifest import (
    ES_NEURONS,
    INPUTS,
    PFC_SOURCES,
    FineTuning,
    Manifest,
    Participant,
)
from agents.neuron_defaults import SELECTIVE_EPSILON

# ---------------------------------------------------------------------------------------------
# The designed weights (the reference's, docs/auction.md). δ is the small "seed" weight that
# fills every entry the design does not set, so no input is entirely ignored.
DELTA = 0.001
"""δ: the weight of an input a neuron should barely notice."""
SENSOR_DESIGN: dict[str, tuple[dict[str, float], float]] = {
    # PG lights up when the price exceeds my willingness to pay b (its price weight, 1/b, is set
    # per patron) and a little when the fish is small (l, w, g below 1): 1/b·p − δ(l+w+g).
    "PG": ({"length": -DELTA, "weight": -DELTA, "gill": -DELTA}, 0.0),
    # SZ grows with length and weight: (l + w)/2.
    "SZ": ({"length": 0.5, "weight": 0.5}, 0.0),
    # LSR follows the buy fraction f of the last round (others are buying: hurry).
    "LSR": ({"buy_fraction": 1.0}, 0.0),
    # ST peaks at the preferred sub-type (½, ½, ½): (st1 + st2 + st3)/3 − ½ = 0 there, less
    # the δ terms of the other inputs (about 0.0085 at the prototype row: ST = 0.58 there).
    "ST": ({"st1": 1 / 3, "st2": 1 / 3, "st3": 1 / 3}, -0.5),
}
"""Per ES neuron: the designed input weights (every other input gets δ) and the bias."""
SENSOR_ACTIVATIONS: dict[str, dict[str, float | str]] = {
    "PG": {"kind": "threshold", "a": 20.0, "c": 1.0, "negative_slope": 0.01},  # p/b > 1: fires
    "SZ": {"kind": "threshold", "a": 5.0, "c": 1.0, "negative_slope": 0.8},  # bigger than 1
    "LSR": {"kind": "threshold", "a": 1.0, "c": 0.5, "negative_slope": 0.01},  # f above ½
    "ST": {"kind": "selective", "epsilon": SELECTIVE_EPSILON},  # exactly the preferred type
}
"""Per ES neuron: its activation and parameters (ST's ε as the reference runs it, 1e-4)."""
DECISION_DESIGN: dict[str, tuple[dict[str, float], float]] = {
    # buy: cheap (−PG), big (SZ), others buying (LSR), my sub-type (ST); base intent 1.
    "B": ({"PG": -1.0, "SZ": 1.0, "LSR": 1.0, "ST": 1.0}, 1.0),
    # hold: price somewhat high (0.8 PG) unless the fish is big (−SZ); bias + hold_bias.
    "L": ({"PG": 0.8, "SZ": -1.0, "LSR": 0.0, "ST": 0.0}, 0.0),
    # quit: price far too high (2 PG overtakes B as PG saturates); bias −0.5 + quit_bias.
    "Q": ({"PG": 2.0, "SZ": 0.0, "LSR": 0.0, "ST": 0.0}, -0.5),
}
"""Per FC neuron: weights from PG, SZ, LSR, ST and the base bias (the reference's)."""
JUDGEMENT_DESIGN: dict[str, dict[str, float]] = {
    "PGL": {"PG": 1.0, "L": 1.0},  # price high and I hold: right
    "BC": {"PG": -1.0, "B": 1.0},  # price low and I buy: right
    "FQ": {"SZ": 1.0, "LSR": 1.0, "ST": 1.0, "Q": 1.0},  # a good, wanted fish and I quit: wrong
}
"""Per PFC judgement neuron: weights from softmax([PG, SZ, LSR, ST, B, L, Q]); zero bias."""
VERDICT_DESIGN: dict[str, tuple[dict[str, float], float]] = {
    "T": ({"PGL": 1.0, "BC": 1.0, "FQ": 0.0}, 0.0),  # true when either "right" judgement fires
    "F": ({"PGL": 0.0, "BC": 0.0, "FQ": 1.0}, 0.05),  # false on a false quit; slight prior
}
"""Per PFC verdict neuron: weights from tanh([PGL, BC, FQ]) and the bias (the reference's)."""
BASE_ITEM = {
    "price": 5.0,  # the opening price of every auction
    "length": 1.0,  # length, weight and gill colour are normalised: 1 is an ordinary fish
    "weight": 1.0,
    "gill": 1.0,
    "st1": 0.5,  # the preferred sub-type (½, ½, ½), the one ST is tuned to
    "st2": 0.5,
    "st3": 0.5,
    "buy_fraction": 0.5,  # f before any vote: half the patrons are assumed to want to buy
}
"""The base item (p, l, w, g, st1, st2, st3, f), by input name: the prototype fish of row 0,
the only row whose votes decide purchases, at the opening price."""
BASE_PRICE = BASE_ITEM["price"]
"""The opening price of an auction (the market's default) and the top of the willingness band."""
WILLINGNESS_TO_PAY_RANGE = (4.8, BASE_PRICE)
"""Every factory patron's willingness to pay b ~ U(4.8, 5.0), which sets PG's price weight 1/b
(the reference's min_buy_price and base_price)."""
HOLD_BIAS_RANGE = (-0.5, 0.5)
"""Honest patrons add hold_bias ~ U(−0.5, 0.5) to L (the reference's)."""
QUIT_BIAS_RANGE = (0.0, 0.5)
"""Honest patrons add quit_bias ~ U(0, 0.5) to Q (the reference's)."""
FINE_TUNE_EPOCHS = (0, 2)
"""Honest fine-tuning epochs ~ randint{0, 1, 2} (the paper's; 0 = no fine-tuning)."""
FINE_TUNE_BATCH = (4, 15)
"""Honest fine-tuning batch size ~ randint{4..15} (the paper's)."""
FINE_TUNE_LR = (1e-7, 1e-4)
"""Honest SGD learning rate ~ U(1e−7, 1e−4) (the paper's)."""
SABOTEUR_HOLD_BIAS = 5.0
"""The saboteur's hold bias: L ≥ 5 − 0.8 − 1 > 3 whatever the input, above B and Q."""
SABOTEUR_BUY_BIAS = -1.0
"""The saboteur's buy bias; its buy weights are all zero, so B = −1 always (inert)."""
# ---------------------------------------------------------------------------------------------


# --- Patron factories -------------------------------------------------------------------------


@functools.cache
def _design(kind: str) -> Manifest:
    """The designed FSN (``honest``: the reference's, with zero hold and quit biases; ``saboteur``:
    inert buy neuron, hold bias +5), validated once; the factories copy it."""
    sensor = {}
    for name, (weights, bias) in SENSOR_DESIGN.items():
        row = {inp: weights.get(inp, DELTA) for inp in INPUTS}
        sensor[name] = {"weights": row, "bias": bias, "activation": SENSOR_ACTIVATIONS[name]}
    decision = {name: {"weights": w, "bias": b} for name, (w, b) in DECISION_DESIGN.items()}
    if kind == "saboteur":
        decision["B"] = {"weights": dict.fromkeys(ES_NEURONS, 0.0), "bias": SABOTEUR_BUY_BIAS}
        decision["L"]["bias"] = SABOTEUR_HOLD_BIAS
    judgement = {
        name: {"weights": {s: w.get(s, 0.0) for s in PFC_SOURCES}, "bias": 0.0}
        for name, w in JUDGEMENT_DESIGN.items()
    }
    verdict = {name: {"weights": w, "bias": b} for name, (w, b) in VERDICT_DESIGN.items()}
    return Manifest.model_validate(
        {
            "participant": kind,
            "external_sensor": sensor,
            "decision": decision,
            "pfc": {"judgement": judgement, "verdict": verdict},
        }
    )


_PARTICIPANT = TypeAdapter(Participant)


def _personalised(
    design: Manifest,
    participant: str,
    description: str,
    willingness_to_pay: float,
    biases: dict[str, float],
    fine_tuning: FineTuning,
) -> Manifest:
    """A copy of ``design`` with PG's price weight 1/b, some FC biases and the given settings
    (frozen sub-models are shared, not copied; nothing here can leave the schema's ranges)."""
    pg = design.external_sensor.PG
    weights = pg.weights.model_copy(update={"price": 1.0 / willingness_to_pay})
    sensor = design.external_sensor.model_copy(
        update={"PG": pg.model_copy(update={"weights": weights})}
    )
    decision = design.decision.model_copy(
        update={
            name: getattr(design.decision, name).model_copy(update={"bias": bias})
            for name, bias in biases.items()
        }
    )
    return design.model_copy(
        update={
            "participant": _PARTICIPANT.validate_python(participant),
            "description": description,
            "external_sensor": sensor,
            "decision": decision,
            "fine_tuning": fine_tuning,
        }
    )


def honest_manifest(
    rng: np.random.Generator,
    participant: str,
    *,
    fine_tune: bool = True,
    base_price: float = WILLINGNESS_TO_PAY_RANGE[1],
    min_buy_price: float = WILLINGNESS_TO_PAY_RANGE[0],
) -> Manifest:
    """An honest FSN (the paper's randomisation): willingness to pay
    b ~ U(min_buy_price, base_price) sets the PG price weight 1/b; hold_bias ~ U(−0.5, 0.5),
    quit_bias ~ U(0, 0.5); fine-tuning epochs ~ {0,1,2}, batch ~ {4..15}, lr ~ U(1e−7, 1e−4).
    The fine-tuning numbers are always drawn (so the same stream gives the same patron either
    way); ``fine_tune=False`` keeps the default settings (no epochs)."""
    if not 0 < min_buy_price <= base_price:
        raise ValueError("need 0 < min_buy_price ≤ base_price")
    b = float(rng.uniform(min_buy_price, base_price))
    hold_bias = float(rng.uniform(*HOLD_BIAS_RANGE))
    quit_bias = float(rng.uniform(*QUIT_BIAS_RANGE))
    epochs = int(rng.integers(FINE_TUNE_EPOCHS[0], FINE_TUNE_EPOCHS[1] + 1))
    batch_size = int(rng.integers(FINE_TUNE_BATCH[0], FINE_TUNE_BATCH[1] + 1))
    lr = float(rng.uniform(*FINE_TUNE_LR))
    settings = (
        FineTuning(epochs=epochs, batch_size=batch_size, learning_rate=lr)
        if fine_tune
        else FineTuning()
    )
    base = DECISION_DESIGN
    return _personalised(
        _design("honest"),
        participant,
        f"Honest negotiator: pays up to {b:.3f}; buys cheap, big, wanted fish of its sub-type.",
        b,
        {"L": base["L"][1] + hold_bias, "Q": base["Q"][1] + quit_bias},
        settings,
    )


def saboteur_manifest(
    rng: np.random.Generator,
    participant: str,
    *,
    base_price: float = WILLINGNESS_TO_PAY_RANGE[1],
    min_buy_price: float = WILLINGNESS_TO_PAY_RANGE[0],
) -> Manifest:
    """A well-formed FSN that always holds, to drag the price down (paper, Fig. D).

    Sensor and judge are the honest design (b ~ U(min_buy_price, base_price)); the buy neuron
    is inert (all weights 0, bias −1, so B = −1) and the hold bias is +5. Every ES activation
    lies in (−1, 1), hence L = 0.8·PG − SZ + 5 > 3.2 while Q = 2·PG − 0.5 < 1.5 and B = −1: hold
    on every input, noise or not. It never fine-tunes."""
    if not 0 < min_buy_price <= base_price:
        raise ValueError("need 0 < min_buy_price ≤ base_price")
    b = float(rng.uniform(min_buy_price, base_price))
    return _personalised(
        _design("saboteur"),
        participant,
        "Saboteur: always holds to push the price down.",
        b,
        {},
        FineTuning(),
    )
