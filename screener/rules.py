"""Semantic rules: each named weight read against the meaning the paper gives its neuron.

Paper, "The Server and Fish Sale Negotiator": PG lights up when the price is above the
participant's willingness to pay (and a little when the fish is poor), SZ grows with length and
weight, LSR with the previous buy fraction (others are rushing), ST peaks at the preferred
sub-type; B is driven down by PG and up by SZ, LSR, ST; L (hold, want a lower price) and Q (quit)
are driven by PG. The PFC judges: holding at a high price (PGL) and buying cheap (BC) are right
(T), quitting a good fish (FQ) is wrong (F). Every rule below is vectorised over a batch of P
manifests; the thresholds live in ``screener.limits``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from agents.manifest import DECISIONS, ES_NEURONS, INPUTS, JUDGEMENTS, PFC_SOURCES, VERDICTS
from agents.negotiator import SELECTIVE, THRESHOLD, FSNBatch
from screener import limits
from screener.findings import INPUT_WORDS, ROLE, Array, Finding, Mask, finding, fmt_price

PG, SZ, LSR, ST = range(4)
PRICE, LENGTH, WEIGHT, GILL, ST1, ST2, ST3, DEMAND = range(8)
QUALITY_INPUTS = (LENGTH, WEIGHT, GILL)
SUBTYPE_INPUTS = (ST1, ST2, ST3)

# The meaning of each connection (the paper's design, read as signs). Per connection: the sign
# its weight must have, whether the meaning relies on it (then it must also carry at least
# MIN_DESIGNED_WEIGHT) or it is only forbidden from pointing the wrong way (then it may drift by
# SIGN_TOLERANCE), and what the model does if the sign is wrong.
SENSOR_INPUTS = {
    "PG": (PRICE,),
    "SZ": (LENGTH, WEIGHT),
    "LSR": (DEMAND,),
    "ST": SUBTYPE_INPUTS,
}
"""The inputs each ES neuron is named after."""
SENSOR_ACTIVATION = {"PG": THRESHOLD, "SZ": THRESHOLD, "LSR": THRESHOLD, "ST": SELECTIVE}
"""The activation kind each ES neuron's meaning needs: 'rises past a level' or 'this one only'."""
DECISION_MEANING: dict[tuple[str, str], tuple[int, bool, str]] = {
    ("B", "PG"): (-1, True, "buys more as the price rises"),
    ("B", "SZ"): (+1, True, "buys less, the bigger the fish"),
    ("B", "LSR"): (+1, True, "buys less when the others rush to buy"),
    ("B", "ST"): (+1, True, "buys less when the fish is of its preferred sub-type"),
    ("L", "PG"): (+1, True, "holds less as the price rises"),
    ("L", "SZ"): (-1, False, "holds out for a lower price more, the bigger the fish"),
    ("L", "LSR"): (-1, False, "holds back more when the others rush to buy"),
    ("L", "ST"): (-1, False, "holds back more when the fish is of its preferred sub-type"),
    ("Q", "PG"): (+1, True, "quits less as the price rises"),
    ("Q", "SZ"): (-1, False, "quits more, the bigger the fish"),
    ("Q", "LSR"): (-1, False, "quits more when the others rush to buy"),
    ("Q", "ST"): (-1, False, "quits more when the fish is of its preferred sub-type"),
}
"""FC (target, source) → (sign, relied upon, what a wrong sign makes the model do)."""
JUDGEMENT_MEANING: dict[tuple[str, str], tuple[int, bool, str]] = {
    ("PGL", "PG"): (+1, True, "counts holding as less right, the higher the price"),
    ("PGL", "L"): (+1, True, "does not count holding at a high price as right"),
    ("BC", "PG"): (-1, True, "counts buying as more right, the higher the price"),
    ("BC", "B"): (+1, True, "does not count buying cheap as right"),
    ("FQ", "SZ"): (+1, True, "does not count quitting a big fish as a false quit"),
    ("FQ", "LSR"): (+1, True, "does not count quitting in a rush as a false quit"),
    ("FQ", "ST"): (+1, True, "does not count quitting its preferred sub-type as a false quit"),
    ("FQ", "Q"): (+1, True, "does not count quitting as a false quit"),
}
"""PFC judgement (target, source) → (sign, relied upon, consequence); every other source may
carry at most PFC_OFF_DESIGN_LIMIT."""
VERDICT_MEANING: dict[tuple[str, str], tuple[int, bool, str]] = {
    ("T", "PGL"): (+1, True, "judges holding at a high price to be wrong"),
    ("T", "BC"): (+1, True, "judges buying cheap to be wrong"),
    ("T", "FQ"): (-1, False, "judges a false quit to be right"),
    ("F", "PGL"): (-1, False, "judges holding at a high price to be wrong"),
    ("F", "BC"): (-1, False, "judges buying cheap to be wrong"),
    ("F", "FQ"): (+1, True, "does not judge a false quit to be wrong"),
}
"""PFC verdict (target, source) → (sign, relied upon, consequence)."""
NAMED = np.array([[j in SENSOR_INPUTS[name] for j in range(8)] for name in ES_NEURONS])
"""(4, 8): True where an ES neuron is named after the input."""
SPANS = np.array(
    [limits.PRICE_SPAN]
    + [limits.QUALITY_SPAN] * 3
    + [limits.SUBTYPE_SPAN] * 3
    + [limits.DEMAND_SPAN]
)
"""Range of each input over which its influence on a neuron is weighed."""
BASE = np.array(limits.BASE_ROW)
SUBTYPES = np.array(list(itertools.product((0.5, -0.5), repeat=3)))
"""The 8 sub-types; row 0 is the preferred (½, ½, ½)."""


@dataclasses.dataclass(frozen=True)
class Numbers:
    """A batch's numbers as float64 arrays (leading patron axis P)."""

    es_weight: Array
    es_bias: Array
    es_kind: Array
    es_a: Array
    es_c: Array
    es_epsilon: Array
    fc_weight: Array
    fc_bias: Array
    judgement_weight: Array
    judgement_bias: Array
    verdict_weight: Array
    verdict_bias: Array
    noise_std: Array
    noise_mask: Array
    learning_rate: Array
    epochs: Array

    @classmethod
    def of(cls, batch: FSNBatch) -> Numbers:
        """Read the arrays out of a batch."""
        names = [f.name for f in dataclasses.fields(cls)]
        return cls(**{name: getattr(batch, name).double().numpy() for name in names})

    @functools.cached_property
    def willingness_to_pay(self) -> Array:
        """The price where PG crosses its threshold on the base fish (NaN if PG does not rise
        with the price)."""
        return _reference(self, PG)


def _weights_phrase(target: str, source: str, weight: float) -> str:
    return f"{ROLE[target]} {target} has weight {weight:+.3g} from {source}, {ROLE[source]}"


def _sign_message(
    target: str, source: str, weights: Array, meaning: tuple[int, bool, str]
) -> Callable[[int], str]:
    sign, _, consequence = meaning

    def message(p: int) -> str:
        w = float(weights[p])
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

    return message


def _stray_message(target: str, source: str, weights: Array) -> Callable[[int], str]:
    def message(p: int) -> str:
        return (
            f"{_weights_phrase(target, source, weights[p])}: it is not about {source} (at most "
            f"{limits.PFC_OFF_DESIGN_LIMIT:g} in size)"
        )

    return message


def _connections(
    rule: str,
    weights: Array,
    targets: tuple[str, ...],
    sources: tuple[str, ...],
    meaning: dict[tuple[str, str], tuple[int, bool, str]],
    stray_rule: str | None = None,
) -> list[Finding]:
    """Every connection of a layer (weights (P, targets, sources)) against its meaning: a wrong
    sign beyond SIGN_TOLERANCE, a relied-upon weight below MIN_DESIGNED_WEIGHT, and (with
    ``stray_rule``) a connection the meaning does not list above PFC_OFF_DESIGN_LIMIT."""
    sign = np.zeros((len(targets), len(sources)))
    floor = np.zeros_like(sign)
    for (t, s), (wanted, relied, _) in meaning.items():
        i, j = targets.index(t), sources.index(s)
        sign[i, j] = wanted
        floor[i, j] = limits.MIN_DESIGNED_WEIGHT if relied else -limits.SIGN_TOLERANCE
    wrong = weights * sign < floor
    found = [
        Finding(rule, t, wrong[:, targets.index(t), sources.index(s)],
                _sign_message(t, s, weights[:, targets.index(t), sources.index(s)], m))
        for (t, s), m in meaning.items()
    ]  # fmt: skip
    if stray_rule is not None:
        stray = (sign == 0) & (np.abs(weights) > limits.PFC_OFF_DESIGN_LIMIT)
        for i, j in zip(*np.nonzero(sign == 0), strict=True):
            t, s = targets[i], sources[j]
            found.append(
                Finding(stray_rule, t, stray[:, i, j], _stray_message(t, s, weights[:, i, j]))
            )
    return found


def _reference(n: Numbers, neuron: int) -> Array:
    """Where a threshold neuron crosses its centre c on the base item, as a value of the inputs
    it is named after (moved together): (c − bias − other inputs) / Σ named weights; NaN unless
    the named weights sum to more than 0."""
    named = list(SENSOR_INPUTS[ES_NEURONS[neuron]])
    weights = n.es_weight[:, neuron]
    slope = weights[:, named].sum(axis=1)
    rest = weights @ BASE - weights[:, named] @ BASE[named] + n.es_bias[:, neuron]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(slope > 0, (n.es_c[:, neuron] - rest) / slope, np.nan)


def _outside(values: Array, low: float, high: float) -> Mask:
    """Outside [low, high] (NaN counts as inside: another rule reports it)."""
    return (values < low) | (values > high)


def activation_findings(n: Numbers) -> list[Finding]:
    """Each ES neuron uses the activation its meaning needs, with sane parameters."""
    found = []
    for i, name in enumerate(ES_NEURONS):
        wanted = SENSOR_ACTIVATION[name]
        words = "a threshold (it must rise once its input passes a level)"
        if wanted == SELECTIVE:
            words = "selective (it must light up for one sub-type only)"
        found.append(
            finding(
                "activation-kind",
                name,
                n.es_kind[:, i] != wanted,
                _constant(f"{ROLE[name]} {name} must be {words}"),
            )
        )
    eps = n.es_epsilon[:, ST]
    low, high = limits.SELECTIVE_EPSILON_RANGE
    found.append(
        finding(
            "selective-width",
            "ST",
            (n.es_kind[:, ST] == SELECTIVE) & _outside(eps, low, high),
            lambda p: (
                f"ST's selective ε = {eps[p]:.3g} gives a peak half-width √ε = "
                f"{np.sqrt(eps[p]):.3g}, outside {np.sqrt(low):g} to {np.sqrt(high):g}: "
                "it is blind or sees every sub-type alike"
            ),
        )
    )
    return found


def price_findings(n: Numbers) -> list[Finding]:
    """PG: rises with price, declares a plausible willingness to pay, not dearer when better."""
    w_price = n.es_weight[:, PG, PRICE]
    threshold = n.es_kind[:, PG] == THRESHOLD
    wtp = n.willingness_to_pay
    low, high = (f * limits.BASE_PRICE for f in limits.WILLINGNESS_TO_PAY_BAND)
    found = [
        _rises(
            "rises-with-price",
            n,
            PG,
            PRICE,
            "it does not light up as the price rises, so the model cannot tell a dear fish from "
            "a cheap one",
        ),
        finding(
            "willingness-to-pay",
            "PG",
            threshold & _outside(wtp, low, high),
            lambda p: (
                f"PG crosses its threshold at price {fmt_price(wtp[p])} on the base fish: a "
                f"declared willingness to pay of {wtp[p] / limits.BASE_PRICE:.2g}× the base "
                f"price {limits.BASE_PRICE:g}, outside the plausible {fmt_price(low)} to "
                f"{fmt_price(high)}"
            ),
        ),
    ]
    for q in QUALITY_INPUTS:
        with np.errstate(divide="ignore", invalid="ignore"):
            drop = np.where(
                w_price > 0, n.es_weight[:, PG, q] * limits.QUALITY_SPAN / w_price, np.nan
            )
        found.append(
            finding(
                "falls-with-quality",
                "PG",
                drop > limits.QUALITY_PRICE_TOLERANCE,
                _quality_message(n, q, drop),
            )
        )
    return found


def _constant(text: str) -> Callable[[int], str]:
    return lambda p: text


def _quality_message(n: Numbers, q: int, drop: Array) -> Callable[[int], str]:
    def message(p: int) -> str:
        return (
            f"PG has weight {n.es_weight[p, PG, q]:+.3g} from {INPUT_WORDS[INPUTS[q]]}: a better "
            "fish looks dearer to it, and across the fish on sale its willingness to pay drops "
            f"by {drop[p]:.2f}"
        )

    return message


def _sensor_sign_message(
    n: Numbers, neuron: int, inp: int, consequence: str
) -> Callable[[int], str]:
    name = ES_NEURONS[neuron]

    def message(p: int) -> str:
        return (
            f"{name}, {ROLE[name]}, has weight {n.es_weight[p, neuron, inp]:+.3g} from "
            f"{INPUT_WORDS[INPUTS[inp]]}: {consequence}"
        )

    return message


def _sharpness(
    n: Numbers, neuron: int, gain: Array, unit: str, ok_sign: Mask | None = None
) -> Finding:
    name = ES_NEURONS[neuron]
    design = limits.DESIGN_SHARPNESS[name]
    low, high = design / limits.SHARPNESS_FACTOR, design * limits.SHARPNESS_FACTOR
    applies = n.es_kind[:, neuron] == THRESHOLD
    if ok_sign is not None:
        applies &= ok_sign
    return finding(
        "sharpness",
        name,
        applies & _outside(gain, low, high),
        lambda p: (
            f"{ROLE[name]} {name} changes its threshold argument by {gain[p]:.3g} per "
            f"{unit} (design {design:g}; allowed {low:g} to {high:g}): "
            + ("a hidden step" if gain[p] > high else "nearly flat, it hardly reacts")
        ),
    )


def _rises(rule: str, n: Numbers, neuron: int, inp: int, consequence: str) -> Finding:
    """The ES neuron's weight from an input it is named after must be positive."""
    return finding(
        rule,
        ES_NEURONS[neuron],
        n.es_weight[:, neuron, inp] <= 0,
        _sensor_sign_message(n, neuron, inp, consequence),
    )


def _reference_finding(
    rule: str, n: Numbers, neuron: int, band: tuple[float, float], what: str, why: str
) -> Finding:
    """The threshold neuron's reference point (``_reference``) must lie in ``band``."""
    name, (low, high) = ES_NEURONS[neuron], band
    point = _reference(n, neuron)
    return finding(
        rule,
        name,
        (n.es_kind[:, neuron] == THRESHOLD) & _outside(point, low, high),
        lambda p: (
            f"{name} crosses its threshold at {what} {point[p]:.2f}, outside {low:g} to "
            f"{high:g}: {why}"
        ),
    )


def size_demand_findings(n: Numbers) -> list[Finding]:
    """SZ rises with length and weight around a normal size; LSR rises with the buy fraction."""
    grows = "it does not grow with the fish"
    w_demand = n.es_weight[:, LSR, DEMAND]
    found = [
        *(_rises("rises-with-size", n, SZ, inp, grows) for inp in SENSOR_INPUTS["SZ"]),
        _reference_finding(
            "size-reference", n, SZ, limits.SIZE_REFERENCE_BAND, "size",
            "it reads the same for every fish on sale",
        ),
        _rises("rises-with-demand", n, LSR, DEMAND, "it does not rise when the others rush to buy"),
        _reference_finding(
            "demand-reference", n, LSR, limits.DEMAND_REFERENCE_BAND, "buy fraction",
            "a rush level that never occurs",
        ),
    ]  # fmt: skip
    size_gain = n.es_a[:, SZ] * n.es_weight[:, SZ, list(SENSOR_INPUTS["SZ"])].sum(axis=1)
    rush_gain = n.es_a[:, LSR] * w_demand
    wtp = n.willingness_to_pay
    price_gain = n.es_a[:, PG] * n.es_weight[:, PG, PRICE] * wtp
    found += [
        _sharpness(n, PG, price_gain, "100% of its willingness to pay", ~np.isnan(wtp)),
        _sharpness(n, SZ, size_gain, "unit of size", size_gain > 0),
        _sharpness(n, LSR, rush_gain, "unit of buy fraction", w_demand > 0),
    ]
    return found


def subtype_findings(n: Numbers) -> list[Finding]:
    """ST: positive weights on the sub-type flags and a selective peak at (½, ½, ½)."""
    flags = "the preferred sub-type (½, ½, ½) needs a positive weight on every flag"
    found = [_rises("subtype-weights", n, ST, inp, flags) for inp in SUBTYPE_INPUTS]
    others = np.ones(8, dtype=bool)
    others[list(SUBTYPE_INPUTS)] = False
    rest = n.es_weight[:, ST, others] @ BASE[others] + n.es_bias[:, ST]
    pre = rest[:, None] + n.es_weight[:, ST, list(SUBTYPE_INPUTS)] @ SUBTYPES.T  # (P, 8)
    eps = n.es_epsilon[:, ST, None]
    response = eps / (eps + pre * pre)
    rival = 1 + response[:, 1:].argmax(axis=1)
    best_rival = response[np.arange(len(rival)), rival]
    selective = n.es_kind[:, ST] == SELECTIVE

    def message(p: int) -> str:
        s = ", ".join("½" if v > 0 else "−½" for v in SUBTYPES[rival[p]])
        return (
            f"ST reaches {best_rival[p]:.3g} at sub-type ({s}) against {response[p, 0]:.3g} at "
            "the preferred (½, ½, ½): its bias and weights do not make the preferred sub-type "
            "its clear peak"
        )

    found.append(
        finding(
            "selective-peak",
            "ST",
            selective & ~(best_rival <= limits.SELECTIVITY_RATIO * response[:, 0]),
            message,
        )
    )
    return found


def _off_design_message(n: Numbers, i: int, share: Array, worst: Array) -> Callable[[int], str]:
    name = ES_NEURONS[i]
    named_words = " and ".join(INPUT_WORDS[INPUTS[j]] for j in SENSOR_INPUTS[name])

    def message(p: int) -> str:
        j = int(worst[p, i])
        return (
            f"{ROLE[name]} {name} has weight {n.es_weight[p, i, j]:+.3g} from "
            f"{INPUT_WORDS[INPUTS[j]]}, moving it {share[p, i, j]:.2f}× as much as {named_words}: "
            "it is not about what its name says"
        )

    return message


def off_design_findings(n: Numbers) -> list[Finding]:
    """No ES neuron is driven by an input it is not named after."""
    influence = np.abs(n.es_weight) * SPANS  # (P, 4, 8)
    own = (influence * NAMED).sum(axis=2, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(NAMED, 0.0, np.where(own > 0, influence / own, np.inf * (influence > 0)))
    share = np.nan_to_num(share, nan=0.0)
    worst = share.argmax(axis=2)  # (P, 4)
    failed = share.max(axis=2) > limits.OFF_DESIGN_SHARE
    return [
        Finding("off-design-input", name, failed[:, i], _off_design_message(n, i, share, worst))
        for i, name in enumerate(ES_NEURONS)
    ]


def decision_findings(n: Numbers) -> list[Finding]:
    """FC: the sign of every connection, and buying as the default intent."""
    found = _connections("decision-sign", n.fc_weight, DECISIONS, ES_NEURONS, DECISION_MEANING)
    bias = n.fc_bias
    found.append(
        finding(
            "buy-intent",
            "B",
            ~(bias[:, 0] > bias[:, 1:].max(axis=1)),
            lambda p: (
                f"the buy neuron B has bias {bias[p, 0]:+.3g}, not above the hold neuron L "
                f"({bias[p, 1]:+.3g}) and the quit neuron Q ({bias[p, 2]:+.3g}): with every "
                "sensor quiet (an ordinary fish at its own price) the model does not buy"
            ),
        )
    )
    return found


def _bias_message(target: str, bias: Array) -> Callable[[int], str]:
    def message(p: int) -> str:
        return (
            f"{ROLE[target]} {target} has bias {bias[p]:+.3g} (at most "
            f"{limits.JUDGEMENT_BIAS_LIMIT:g} in size): it is decided before it reads anything"
        )

    return message


def pfc_findings(n: Numbers) -> list[Finding]:
    """PFC: the judgements read what they are named after; T rewards the sensible decisions."""
    found = _connections(
        "judgement-sign",
        n.judgement_weight,
        JUDGEMENTS,
        PFC_SOURCES,
        JUDGEMENT_MEANING,
        stray_rule="judgement-off-design",
    )
    biased = np.abs(n.judgement_bias) > limits.JUDGEMENT_BIAS_LIMIT
    for j, target in enumerate(JUDGEMENTS):
        found.append(
            Finding(
                "judgement-bias",
                target,
                biased[:, j],
                _bias_message(target, n.judgement_bias[:, j]),
            )
        )
    found += _connections("verdict-sign", n.verdict_weight, VERDICTS, JUDGEMENTS, VERDICT_MEANING)
    gap = n.verdict_bias[:, 0] - n.verdict_bias[:, 1]
    found.append(
        finding(
            "verdict-bias",
            "T",
            np.abs(gap) > limits.VERDICT_BIAS_GAP_LIMIT,
            lambda p: (
                f"the verdicts' biases differ by {gap[p]:+.3g} (T − F; at most "
                f"{limits.VERDICT_BIAS_GAP_LIMIT:g} in size): the PFC calls every decision "
                f"{'right' if gap[p] > 0 else 'wrong'} before judging it, and fine-tuning follows"
            ),
        )
    )
    return found


def setting_findings(n: Numbers) -> list[Finding]:
    """Augmentation and fine-tuning settings within sane bounds."""
    std, lr, epochs = n.noise_std, n.learning_rate, n.epochs
    subtype_cols = [INPUTS.index(name) for name in limits.NOISELESS_SUBTYPES]
    jittered = n.noise_mask[:, subtype_cols].max(axis=1) > 0
    return [
        finding(
            "augmentation-noise",
            "PG",
            std > limits.NOISE_STD_LIMIT,
            lambda p: (
                f"augmentation noise σ = {std[p]:.3g} jitters the price PG reads by about "
                f"±{std[p]:.2f} (at most {limits.NOISE_STD_LIMIT:g}): its votes near its price "
                "become random"
            ),
        ),
        finding(
            "augmentation-subtypes",
            "ST",
            (std > 0) & jittered,
            lambda p: (
                "augmentation jitters the sub-type flags: they are discrete, and noise "
                f"σ = {std[p]:.3g} blurs the selective ST neuron's peak"
            ),
        ),
        finding(
            "fine-tuning",
            "T",
            (lr > limits.LEARNING_RATE_LIMIT) | (epochs > limits.EPOCHS_LIMIT),
            lambda p: (
                f"fine-tuning with learning rate {lr[p]:.3g} for {int(epochs[p])} epochs "
                f"(at most {limits.LEARNING_RATE_LIMIT:g} and {limits.EPOCHS_LIMIT}) would push "
                "the model towards the PFC verdict T/F faster than re-screening can follow"
            ),
        ),
    ]


def magnitude_findings(n: Numbers) -> list[Finding]:
    """No gigantic numbers anywhere: |weight|, |bias|, |threshold centre| ≤ MAGNITUDE_LIMIT."""
    threshold_like = (n.es_kind != SELECTIVE)[..., None]
    es_c = np.where(threshold_like[..., 0], n.es_c, 0.0)
    layers = [
        (ES_NEURONS, np.concatenate([n.es_weight, n.es_bias[..., None], es_c[..., None]], -1),
         [*INPUTS, "bias", "threshold centre c"]),
        (DECISIONS, np.concatenate([n.fc_weight, n.fc_bias[..., None]], -1),
         [*ES_NEURONS, "bias"]),
        (JUDGEMENTS, np.concatenate([n.judgement_weight, n.judgement_bias[..., None]], -1),
         [*PFC_SOURCES, "bias"]),
        (VERDICTS, np.concatenate([n.verdict_weight, n.verdict_bias[..., None]], -1),
         [*JUDGEMENTS, "bias"]),
    ]  # fmt: skip
    found = []
    for neurons, values, columns in layers:
        size = np.abs(values)
        worst = size.argmax(axis=2)  # (P, neurons)
        failed = size.max(axis=2) > limits.MAGNITUDE_LIMIT
        found += [
            Finding(
                "magnitude", name, failed[:, i], _magnitude_message(i, name, values, worst, columns)
            )
            for i, name in enumerate(neurons)
        ]
    return found


def _magnitude_message(
    i: int, name: str, values: Array, worst: npt.NDArray[np.intp], columns: list[str]
) -> Callable[[int], str]:
    def message(p: int) -> str:
        k = int(worst[p, i])
        what = (
            columns[k]
            if columns[k] in ("bias", "threshold centre c")
            else f"weight from {columns[k]}"
        )
        return (
            f"{ROLE[name]} {name} has {what} {values[p, i, k]:+.3g}, beyond "
            f"±{limits.MAGNITUDE_LIMIT:g}: a gigantic number hides its real effect"
        )

    return message


def semantic_findings(batch: FSNBatch) -> list[Finding]:
    """Every semantic rule over the batch."""
    n = Numbers.of(batch)
    return [
        *magnitude_findings(n),
        *activation_findings(n),
        *price_findings(n),
        *size_demand_findings(n),
        *subtype_findings(n),
        *off_design_findings(n),
        *decision_findings(n),
        *pfc_findings(n),
        *setting_findings(n),
    ]
