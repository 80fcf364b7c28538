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

import numpy as np
import numpy.typing as npt

from agents.batch import ACTIVATION_KINDS, SELECTIVE, THRESHOLD, FSNBatch
from agents.manifest import DECISIONS, ES_NEURONS, INPUTS, JUDGEMENTS, PFC_SOURCES, VERDICTS
from agents.negotiator import SENSOR_ACTIVATIONS
from screener import limits
from screener.findings import INPUT_WORDS, ROLE, Array, Checks, Mask, check, fmt_price

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
SENSOR_ACTIVATION = {
    name: ACTIVATION_KINDS.index(str(act["kind"])) for name, act in SENSOR_ACTIVATIONS.items()
}
"""The activation kind each ES neuron's meaning needs, the design's: 'rises past a level'
(threshold: PG, SZ, LSR) or 'this one only' (selective: ST)."""
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


NAMED_COLUMNS = tuple(
    (np.array(SENSOR_INPUTS[name], dtype=np.intp), BASE[list(SENSOR_INPUTS[name])])
    for name in ES_NEURONS
)
"""Per ES neuron: the inputs it is named after, and their values on the base item."""
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
"""Allowed sharpness of the threshold neurons PG, SZ, LSR (``limits.SHARPNESS_FACTOR``)."""
MAGNITUDE_LAYERS = (
    (ES_NEURONS, (*INPUTS, "bias", "threshold centre c")),
    (DECISIONS, (*ES_NEURONS, "bias")),
    (JUDGEMENTS, (*PFC_SOURCES, "bias")),
    (VERDICTS, (*JUDGEMENTS, "bias")),
)
"""Per layer, its neurons and the numbers of each that the magnitude rule reads."""
MAGNITUDE_NEURONS = tuple(name for names, _ in MAGNITUDE_LAYERS for name in names)
MAGNITUDE_COLUMNS = tuple(columns for names, columns in MAGNITUDE_LAYERS for _ in names)


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
        return cls(**{name: getattr(batch, name).double().numpy() for name in _NUMBER_FIELDS})

    @functools.cached_property
    def willingness_to_pay(self) -> Array:
        """The price where PG crosses its threshold on the base fish (NaN if PG does not rise
        with the price)."""
        return _reference(self, PG)


_NUMBER_FIELDS = tuple(f.name for f in dataclasses.fields(Numbers))


@dataclasses.dataclass(frozen=True)
class _Layer:
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


def _layer(
    targets: tuple[str, ...],
    sources: tuple[str, ...],
    meaning: dict[tuple[str, str], tuple[int, bool, str]],
) -> _Layer:
    sign = np.zeros((len(targets), len(sources)))
    floor = np.zeros_like(sign)
    for (t, s), (wanted, relied, _) in meaning.items():
        i, j = targets.index(t), sources.index(s)
        sign[i, j] = wanted
        floor[i, j] = limits.MIN_DESIGNED_WEIGHT if relied else -limits.SIGN_TOLERANCE
    rows = np.array([targets.index(t) for t, _ in meaning], dtype=np.intp)
    cols = np.array([sources.index(s) for _, s in meaning], dtype=np.intp)
    stray_rows, stray_cols = np.nonzero(sign == 0)
    return _Layer(
        targets, sources, tuple(meaning.values()), sign, floor, rows, cols, stray_rows, stray_cols
    )


DECISION_LAYER = _layer(DECISIONS, ES_NEURONS, DECISION_MEANING)
JUDGEMENT_LAYER = _layer(JUDGEMENTS, PFC_SOURCES, JUDGEMENT_MEANING)
VERDICT_LAYER = _layer(VERDICTS, JUDGEMENTS, VERDICT_MEANING)


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


def _connections(
    rule: str, weights: Array, layer: _Layer, stray_rule: str | None = None
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


def _reference(n: Numbers, neuron: int) -> Array:
    """Where a threshold neuron crosses its centre c on the base item, as a value of the inputs
    it is named after (moved together): (c − bias − other inputs) / Σ named weights; NaN unless
    the named weights sum to more than 0."""
    named, base_named = NAMED_COLUMNS[neuron]
    weights = n.es_weight[:, neuron]
    named_weights = weights[:, named]
    slope = named_weights.sum(axis=1)
    rest = weights @ BASE - named_weights @ base_named + n.es_bias[:, neuron]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(slope > 0, (n.es_c[:, neuron] - rest) / slope, np.nan)


def _outside(values: Array, low: float | Array, high: float | Array) -> Mask:
    """Outside [low, high] (NaN counts as inside: another rule reports it)."""
    return (values < low) | (values > high)


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
            (n.es_kind[:, ST] == SELECTIVE) & _outside(eps, low, high),
            lambda p: (
                f"ST's selective ε = {eps[p]:.3g} gives a peak half-width √ε = "
                f"{np.sqrt(eps[p]):.3g}, outside {np.sqrt(low):g} to {np.sqrt(high):g}: "
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
            f"PG has weight {n.es_weight[p, PG, q]:+.3g} from {INPUT_WORDS[INPUTS[q]]}: a better "
            "fish looks dearer to it, and across the fish on sale its willingness to pay drops "
            f"by {drop[p, k]:.2f}"
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
            threshold & _outside(wtp, low, high),
            lambda p: (
                f"PG crosses its threshold at price {fmt_price(wtp[p])} on the base fish: a "
                f"declared willingness to pay of {wtp[p] / limits.BASE_PRICE:.2g}× the base "
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
            f"{name}, {ROLE[name]}, has weight {n.es_weight[p, neuron, inp]:+.3g} from "
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
            f"{ROLE[name]} {name} changes its threshold argument by {g:.3g} per "
            f"{SHARPNESS_UNITS[k]} (design {SHARPNESS_DESIGN[k]:g}; allowed {low:g} to "
            f"{high:g}): " + ("a hidden step" if g > high else "nearly flat, it hardly reacts")
        )

    failed = applies & _outside(gain, SHARPNESS_LOW, SHARPNESS_HIGH)
    return Checks(("sharpness",) * len(names), names, failed, message)


def _reference_check(
    rule: str, n: Numbers, neuron: int, band: tuple[float, float], what: str, why: str
) -> Checks:
    """The threshold neuron's reference point (``_reference``) must lie in ``band``."""
    name, (low, high) = ES_NEURONS[neuron], band
    point = _reference(n, neuron)
    return check(
        rule,
        name,
        (n.es_kind[:, neuron] == THRESHOLD) & _outside(point, low, high),
        lambda p: (
            f"{name} crosses its threshold at {what} {point[p]:.2f}, outside {low:g} to "
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
            f"{ROLE[name]} {name} has weight {n.es_weight[p, i, j]:+.3g} from "
            f"{INPUT_WORDS[INPUTS[j]]}, moving it {share[p, i, j]:.2f}× as much as {named_words}: "
            "it is not about what its name says"
        )

    failed = share.max(axis=2) > limits.OFF_DESIGN_SHARE
    return [Checks(("off-design-input",) * len(ES_NEURONS), ES_NEURONS, failed, message)]


def decision_checks(n: Numbers) -> list[Checks]:
    """FC: the sign of every connection, and buying as the default intent."""
    bias = n.fc_bias
    return [
        *_connections("decision-sign", n.fc_weight, DECISION_LAYER),
        check(
            "buy-intent",
            "B",
            ~(bias[:, 0] > bias[:, 1:].max(axis=1)),
            lambda p: (
                f"the buy neuron B has bias {bias[p, 0]:+.3g}, not above the hold neuron L "
                f"({bias[p, 1]:+.3g}) and the quit neuron Q ({bias[p, 2]:+.3g}): with every "
                "sensor quiet (an ordinary fish at its own price) the model does not buy"
            ),
        ),
    ]


def pfc_checks(n: Numbers) -> list[Checks]:
    """PFC: the judgements read what they are named after; T rewards the sensible decisions."""
    judgement_bias = n.judgement_bias

    def bias_message(j: int, p: int) -> str:
        target = JUDGEMENTS[j]
        return (
            f"{ROLE[target]} {target} has bias {judgement_bias[p, j]:+.3g} (at most "
            f"{limits.JUDGEMENT_BIAS_LIMIT:g} in size): it is decided before it reads anything"
        )

    gap = n.verdict_bias[:, 0] - n.verdict_bias[:, 1]
    return [
        *_connections(
            "judgement-sign", n.judgement_weight, JUDGEMENT_LAYER, "judgement-off-design"
        ),
        Checks(
            ("judgement-bias",) * len(JUDGEMENTS),
            JUDGEMENTS,
            np.abs(judgement_bias) > limits.JUDGEMENT_BIAS_LIMIT,
            bias_message,
        ),
        *_connections("verdict-sign", n.verdict_weight, VERDICT_LAYER),
        check(
            "verdict-bias",
            "T",
            np.abs(gap) > limits.VERDICT_BIAS_GAP_LIMIT,
            lambda p: (
                f"the verdicts' biases differ by {gap[p]:+.3g} (T − F; at most "
                f"{limits.VERDICT_BIAS_GAP_LIMIT:g} in size): the PFC calls every decision "
                f"{'right' if gap[p] > 0 else 'wrong'} before judging it, and fine-tuning follows"
            ),
        ),
    ]


def setting_checks(n: Numbers) -> list[Checks]:
    """Augmentation and fine-tuning settings within sane bounds."""
    std, lr, epochs = n.noise_std, n.learning_rate, n.epochs
    subtype_cols = [INPUTS.index(name) for name in limits.NOISELESS_SUBTYPES]
    jittered = n.noise_mask[:, subtype_cols].max(axis=1) > 0
    return [
        check(
            "augmentation-noise",
            "PG",
            std > limits.NOISE_STD_LIMIT,
            lambda p: (
                f"augmentation noise σ = {std[p]:.3g} jitters the price PG reads by about "
                f"±{std[p]:.2f} (at most {limits.NOISE_STD_LIMIT:g}): its votes near its price "
                "become random"
            ),
        ),
        check(
            "augmentation-subtypes",
            "ST",
            (std > 0) & jittered,
            lambda p: (
                "augmentation jitters the sub-type flags: they are discrete, and noise "
                f"σ = {std[p]:.3g} blurs the selective ST neuron's peak"
            ),
        ),
        check(
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


def magnitude_checks(n: Numbers) -> list[Checks]:
    """No gigantic numbers anywhere: |weight|, |bias|, |threshold centre| ≤ MAGNITUDE_LIMIT."""
    es_c = np.where(n.es_kind != SELECTIVE, n.es_c, 0.0)
    layers = (
        (n.es_weight, n.es_bias, es_c),
        (n.fc_weight, n.fc_bias),
        (n.judgement_weight, n.judgement_bias),
        (n.verdict_weight, n.verdict_bias),
    )
    # One zero-padded (P, neuron, number) table: padding never raises a row's largest |number|.
    width = max(len(columns) for columns in MAGNITUDE_COLUMNS)
    table = np.zeros((len(n.es_weight), len(MAGNITUDE_NEURONS), width))
    start = 0
    for weight, *extra in layers:
        rows, n_sources = slice(start, start + weight.shape[1]), weight.shape[2]
        table[:, rows, :n_sources] = weight
        for c, values in enumerate(extra):
            table[:, rows, n_sources + c] = values
        start = rows.stop

    def message(i: int, p: int) -> str:
        name, columns = MAGNITUDE_NEURONS[i], MAGNITUDE_COLUMNS[i]
        values = table[p, i, : len(columns)]
        k = int(np.abs(values).argmax())
        what = (
            columns[k]
            if columns[k] in ("bias", "threshold centre c")
            else f"weight from {columns[k]}"
        )
        return (
            f"{ROLE[name]} {name} has {what} {values[k]:+.3g}, beyond "
            f"±{limits.MAGNITUDE_LIMIT:g}: a gigantic number hides its real effect"
        )

    failed = np.abs(table).max(axis=2) > limits.MAGNITUDE_LIMIT
    return [Checks(("magnitude",) * len(MAGNITUDE_NEURONS), MAGNITUDE_NEURONS, failed, message)]


def semantic_checks(n: Numbers) -> list[Checks]:
    """Every semantic rule over the batch's numbers, in reporting order."""
    return [
        *magnitude_checks(n),
        *activation_checks(n),
        *price_checks(n),
        *size_demand_checks(n),
        *subtype_checks(n),
        *off_design_checks(n),
        *decision_checks(n),
        *pfc_checks(n),
        *setting_checks(n),
    ]
