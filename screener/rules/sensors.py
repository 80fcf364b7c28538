"""Rules of the external sensors (ES): each neuron PG, SZ, LSR, ST has the activation its
meaning needs, rises with the inputs it is named after, is neither flat nor a hidden step, and
is not driven by other inputs; PG declares a plausible willingness to pay."""

from __future__ import annotations

import numpy as np

from agents.batch import ACTIVATION_KINDS, SELECTIVE, THRESHOLD
from agents.manifest import ES_NEURONS, INPUTS
from agents.negotiator import SENSOR_ACTIVATIONS
from screener import limits
from screener.findings import INPUT_WORDS, ROLE, Array, Checks, Mask, check, fmt, fmt_price
from screener.rules.numbers import (
    BASE,
    DEMAND,
    LSR,
    PG,
    PRICE,
    QUALITY_INPUTS,
    SENSOR_INPUTS,
    ST,
    SUBTYPE_INPUTS,
    SUBTYPES,
    SZ,
    Numbers,
    outside,
    reference_point,
)

SENSOR_ACTIVATION = {
    name: ACTIVATION_KINDS.index(str(act["kind"])) for name, act in SENSOR_ACTIVATIONS.items()
}
"""The activation kind each ES neuron's meaning needs, the design's: 'rises past a level'
(threshold: PG, SZ, LSR) or 'this one only' (selective: ST)."""
NAMED = np.array([[j in SENSOR_INPUTS[name] for j in range(8)] for name in ES_NEURONS])
"""(4, 8): True where an ES neuron is named after the input."""
SPANS = np.array(
    [limits.PRICE_SPAN]
    + [limits.QUALITY_SPAN] * 3
    + [limits.SUBTYPE_SPAN] * 3
    + [limits.DEMAND_SPAN]
)
"""Range of each input over which its influence on a neuron is weighed."""
OTHER_THAN_SUBTYPES = np.array([j not in SUBTYPE_INPUTS for j in range(8)])
"""(8,): True on the inputs that are not sub-type flags."""
WANTED_KINDS = np.array([SENSOR_ACTIVATION[name] for name in ES_NEURONS], dtype=np.float64)
"""(4,): the activation kind code each ES neuron must have."""
KIND_MESSAGES = tuple(
    f"{ROLE[name]} {name} must be "
    + (
        "selective (it must light up for one sub-type only)"
        if SENSOR_ACTIVATION[name] == SELECTIVE
        else "a threshold (it must rise once its input passes a level)"
    )
    for name in ES_NEURONS
)
SHARPNESS_NEURONS = (PG, SZ, LSR)
SHARPNESS_UNITS = ("100% of its willingness to pay", "unit of size", "unit of buy fraction")
SHARPNESS_DESIGN = np.array([limits.DESIGN_SHARPNESS[ES_NEURONS[i]] for i in SHARPNESS_NEURONS])
SHARPNESS_LOW = SHARPNESS_DESIGN / limits.SHARPNESS_FACTOR
SHARPNESS_HIGH = SHARPNESS_DESIGN * limits.SHARPNESS_FACTOR


def activation_checks(n: Numbers) -> list[Checks]:
    """Each ES neuron uses the activation its meaning needs, with sane parameters."""
    eps = n.es_epsilon[:, ST]
    low, high = limits.SELECTIVE_EPSILON_RANGE
    return [
        Checks(
            ("activation-kind",) * len(ES_NEURONS),
            ES_NEURONS,
            n.es_kind != WANTED_KINDS,
            lambda k, p: KIND_MESSAGES[k],
        ),
        check(
            "selective-width",
            "ST",
            (n.es_kind[:, ST] == SELECTIVE) & outside(eps, low, high),
            lambda p: (
                f"ST's selective ε = {fmt(eps[p])} gives a peak half-width √ε = "
                f"{fmt(np.sqrt(eps[p]))}, outside {np.sqrt(low):g} to {np.sqrt(high):g}: "
                "it is blind or sees every sub-type alike"
            ),
        ),
    ]


def price_checks(n: Numbers) -> list[Checks]:
    """PG: rises with price, declares a plausible willingness to pay, not dearer when better."""
    w_price = n.es_weight[:, PG, PRICE, None]
    threshold = n.es_kind[:, PG] == THRESHOLD
    wtp = n.willingness_to_pay
    low, high = (f * limits.BASE_PRICE for f in limits.WILLINGNESS_TO_PAY_BAND)
    quality = list(QUALITY_INPUTS)
    with np.errstate(divide="ignore", invalid="ignore"):
        drop = np.where(
            w_price > 0, n.es_weight[:, PG, quality] * limits.QUALITY_SPAN / w_price, np.nan
        )

    def quality_message(k: int, p: int) -> str:
        q = QUALITY_INPUTS[k]
        return (
            f"PG has weight {fmt(n.es_weight[p, PG, q], '+.3g')} from "
            f"{INPUT_WORDS[INPUTS[q]]}: a better "
            "fish looks dearer to it, and across the fish on sale its willingness to pay drops "
            f"by {fmt(drop[p, k], '.2f')}"
        )

    return [
        _rises(
            "rises-with-price",
            n,
            PG,
            (PRICE,),
            "it does not light up as the price rises, so the model cannot tell a dear fish from "
            "a cheap one",
        ),
        check(
            "willingness-to-pay",
            "PG",
            threshold & outside(wtp, low, high),
            lambda p: (
                f"PG crosses its threshold at price {fmt_price(wtp[p])} on the base fish: a "
                "declared willingness to pay of "
                f"{fmt(wtp[p] / limits.BASE_PRICE, '.2g')}× the base "
                f"price {limits.BASE_PRICE:g}, outside the plausible {fmt_price(low)} to "
                f"{fmt_price(high)}"
            ),
        ),
        Checks(
            ("falls-with-quality",) * len(quality),
            ("PG",) * len(quality),
            drop > limits.QUALITY_PRICE_TOLERANCE,
            quality_message,
        ),
    ]


def _rises(rule: str, n: Numbers, neuron: int, inputs: tuple[int, ...], consequence: str) -> Checks:
    """The ES neuron's weights from inputs it is named after must be positive."""
    name = ES_NEURONS[neuron]

    def message(k: int, p: int) -> str:
        inp = inputs[k]
        return (
            f"{name}, {ROLE[name]}, has weight {fmt(n.es_weight[p, neuron, inp], '+.3g')} from "
            f"{INPUT_WORDS[INPUTS[inp]]}: {consequence}"
        )

    failed = n.es_weight[:, neuron, list(inputs)] <= 0
    return Checks((rule,) * len(inputs), (name,) * len(inputs), failed, message)


def _sharpness(n: Numbers, gain: Array, ok_sign: Mask) -> Checks:
    """Sharpness of PG, SZ, LSR (``gain`` (P, 3) in units of their own input) within
    SHARPNESS_FACTOR of the design, where the neuron is a threshold and ``ok_sign``."""
    applies = (n.es_kind[:, list(SHARPNESS_NEURONS)] == THRESHOLD) & ok_sign
    names = tuple(ES_NEURONS[i] for i in SHARPNESS_NEURONS)

    def message(k: int, p: int) -> str:
        name, g = names[k], gain[p, k]
        low, high = SHARPNESS_LOW[k], SHARPNESS_HIGH[k]
        return (
            f"{ROLE[name]} {name} changes its threshold argument by {_beyond(g, low, high)} per "
            f"{SHARPNESS_UNITS[k]} (design {SHARPNESS_DESIGN[k]:g}; allowed {low:g} to "
            f"{high:g}): " + ("a hidden step" if g > high else "nearly flat, it hardly reacts")
        )

    slack = limits.SHARPNESS_SLACK
    failed = applies & outside(gain, SHARPNESS_LOW * (1 - slack), SHARPNESS_HIGH * (1 + slack))
    return Checks(("sharpness",) * len(names), names, failed, message)


def _beyond(value: float, low: float, high: float) -> str:
    """``value`` with as many digits as it takes to tell it from the bound it crossed (a
    sharpness of 10.02 against 10 is not "10")."""
    bound = high if value > high else low
    if not np.isfinite(value):
        return fmt(value)
    for digits in range(3, 13):
        words = fmt(value, f".{digits}g")
        if float(words) != bound:
            return words
    return fmt(value)


def _reference_check(
    rule: str, n: Numbers, neuron: int, band: tuple[float, float], what: str, why: str
) -> Checks:
    """The threshold neuron's reference point (``reference_point``) must lie in ``band``."""
    name, (low, high) = ES_NEURONS[neuron], band
    point = reference_point(n, neuron)
    return check(
        rule,
        name,
        (n.es_kind[:, neuron] == THRESHOLD) & outside(point, low, high),
        lambda p: (
            f"{name} crosses its threshold at {what} {fmt(point[p], '.2f')}, outside {low:g} to "
            f"{high:g}: {why}"
        ),
    )


def size_demand_checks(n: Numbers) -> list[Checks]:
    """SZ rises with length and weight around a normal size; LSR rises with the buy fraction;
    PG, SZ and LSR are neither flat nor hidden steps."""
    w_demand = n.es_weight[:, LSR, DEMAND]
    size_gain = n.es_a[:, SZ] * n.es_weight[:, SZ, list(SENSOR_INPUTS["SZ"])].sum(axis=1)
    rush_gain = n.es_a[:, LSR] * w_demand
    wtp = n.willingness_to_pay
    price_gain = n.es_a[:, PG] * n.es_weight[:, PG, PRICE] * wtp
    return [
        _rises("rises-with-size", n, SZ, SENSOR_INPUTS["SZ"], "it does not grow with the fish"),
        _reference_check(
            "size-reference", n, SZ, limits.SIZE_REFERENCE_BAND, "size",
            "it reads the same for every fish on sale",
        ),
        _rises("rises-with-demand", n, LSR, (DEMAND,),
               "it does not rise when the others rush to buy"),
        _reference_check(
            "demand-reference", n, LSR, limits.DEMAND_REFERENCE_BAND, "buy fraction",
            "a rush level that never occurs",
        ),
        _sharpness(
            n,
            np.stack([price_gain, size_gain, rush_gain], axis=1),
            np.stack([~np.isnan(wtp), size_gain > 0, w_demand > 0], axis=1),
        ),
    ]  # fmt: skip


def subtype_checks(n: Numbers) -> list[Checks]:
    """ST: positive weights on the sub-type flags and a selective peak at (½, ½, ½)."""
    flags = "the preferred sub-type (½, ½, ½) needs a positive weight on every flag"
    others = OTHER_THAN_SUBTYPES
    # Row sums, not matrix products, as in ``reference_point``: the same reasons in any batch.
    rest = (n.es_weight[:, ST, others] * BASE[others]).sum(axis=1) + n.es_bias[:, ST]
    on_flags = n.es_weight[:, ST, list(SUBTYPE_INPUTS)]
    pre = rest[:, None] + (on_flags[:, None, :] * SUBTYPES[None, :, :]).sum(axis=2)  # (P, 8)
    eps = n.es_epsilon[:, ST, None]
    response = eps / (eps + pre * pre)
    rival = 1 + response[:, 1:].argmax(axis=1)
    best_rival = response[np.arange(len(rival)), rival]
    selective = n.es_kind[:, ST] == SELECTIVE

    def message(p: int) -> str:
        s = ", ".join("½" if v > 0 else "−½" for v in SUBTYPES[rival[p]])
        return (
            f"ST reaches {fmt(best_rival[p])} at sub-type ({s}) against "
            f"{fmt(response[p, 0])} at "
            "the preferred (½, ½, ½): its bias and weights do not make the preferred sub-type "
            "its clear peak"
        )

    return [
        _rises("subtype-weights", n, ST, SUBTYPE_INPUTS, flags),
        check(
            "selective-peak",
            "ST",
            selective & ~(best_rival <= limits.SELECTIVITY_RATIO * response[:, 0]),
            message,
        ),
    ]


def off_design_checks(n: Numbers) -> list[Checks]:
    """No ES neuron is driven by an input it is not named after."""
    influence = np.abs(n.es_weight) * SPANS  # (P, 4, 8)
    own = (influence * NAMED).sum(axis=2, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(NAMED, 0.0, np.where(own > 0, influence / own, np.inf * (influence > 0)))
    share = np.nan_to_num(share, nan=0.0)

    def message(i: int, p: int) -> str:
        name = ES_NEURONS[i]
        named_words = " and ".join(INPUT_WORDS[INPUTS[j]] for j in SENSOR_INPUTS[name])
        j = int(share[p, i].argmax())
        return (
            f"{ROLE[name]} {name} has weight {fmt(n.es_weight[p, i, j], '+.3g')} from "
            f"{INPUT_WORDS[INPUTS[j]]}, moving it {fmt(share[p, i, j], '.2f')}× as much as "
            f"{named_words}: "
            "it is not about what its name says"
        )

    failed = share.max(axis=2) > limits.OFF_DESIGN_SHARE
    return [
        Checks(("off-design-input",) * len(ES_NEURONS), ES_NEURONS, failed, message),
        _demand_sharpness(n),
    ]


DEMAND_STEP_NEURONS = (PG, SZ, ST)
"""The ES neurons not named after the buy fraction (LSR's own sharpness in it is bounded by
``sharpness``)."""


def demand_gain(n: Numbers) -> Array:
    """(P, 3): how sharply PG, SZ and ST react to the buy fraction, per unit of it: a
    threshold's a·|w_f|, a selective neuron's |w_f| / √ε."""
    neurons = list(DEMAND_STEP_NEURONS)
    weight = np.abs(n.es_weight[:, neurons, DEMAND])
    selective = n.es_kind[:, neurons] == SELECTIVE
    with np.errstate(divide="ignore", invalid="ignore"):
        per_width = np.where(weight > 0, weight / np.sqrt(n.es_epsilon[:, neurons]), 0.0)
    gain: Array = np.nan_to_num(
        np.where(selective, per_width, n.es_a[:, neurons] * weight), nan=np.inf
    )
    return gain


def _demand_sharpness(n: Numbers) -> Checks:
    """PG, SZ and ST react to the buy fraction at most as sharply as LSR may
    (``limits.DEMAND_SHARPNESS_LIMIT``)."""
    gain = demand_gain(n)
    selective = n.es_kind[:, list(DEMAND_STEP_NEURONS)] == SELECTIVE
    limit = limits.DEMAND_SHARPNESS_LIMIT
    names = tuple(ES_NEURONS[i] for i in DEMAND_STEP_NEURONS)

    def message(k: int, p: int) -> str:
        name, g = names[k], gain[p, k]
        how = (
            f"its response halves {fmt(g, '.3g')}× its width per unit of it"
            if selective[p, k]
            else f"it changes its threshold argument by {fmt(g, '.3g')} per unit of it"
        )
        return (
            f"{ROLE[name]} {name} reacts to the buy fraction more sharply than LSR may ({how}, "
            f"at most {limit:g}): a hidden step in the buy fraction, between the fractions a "
            "scan reads"
        )

    failed = gain > limit * (1 + limits.SHARPNESS_SLACK)
    return Checks(("demand-sharpness",) * len(names), names, failed, message)
