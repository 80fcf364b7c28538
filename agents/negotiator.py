"""The Fish Sale Negotiator (FSN), batched over patrons (paper, "The Server and Fish Sale
Negotiator"; spec auction.md §4–§5).

An FSN reads one item row x = (p, l, w, g, st1, st2, st3, f) and decides buy, hold or quit:

* implicit contrastive augmentation: D_ic copies of x (copy 0 clean, the others jittered by
  N(0, σ²) on every channel except the sub-types). The reference's Conv1d with dilation D_ic
  is exactly a per-copy linear map, which is how it is computed here.
* external sensor ES, one linear map of the 8 inputs then an activation per neuron:
  PG (price too high for me), SZ (big fish), LSR (limited supply rush: others are buying),
  ST (my preferred sub-type).
* decision FC: B (buy), L (hold, want a lower price), Q (quit), linear in ES, averaged over the
  copies; the decision is the argmax (ties → the lowest index, i.e. buy before hold before quit).
* prefrontal cortex PFC, the self-judge: softmax of [PG, SZ, LSR, ST, B, L, Q] → judgements PGL
  (holding at a high price), BC (buying cheap), FQ (false quit) → tanh → verdicts T (right) and
  F (wrong), averaged over the copies. SRD fine-tuning minimises CEL([T, F], argmax [T, F]) with
  plain SGD.

All P patrons live in one ``FSNBatch`` (parameters stacked on a leading patron axis), so one
tensor pass evaluates patrons × rows × copies, whatever activation each manifest chose.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from pydantic import TypeAdapter
from torch import Tensor

from agents.manifest import (
    DECISIONS,
    ES_NEURONS,
    INPUTS,
    JUDGEMENTS,
    PFC_SOURCES,
    VERDICTS,
    BelowThresholdActivation,
    FineTuning,
    Manifest,
    Participant,
    SelectiveActivation,
    ThresholdActivation,
)
from agents.neurons import SELECTIVE_EPSILON

ACTIVATION_KINDS = ("threshold", "below_threshold", "selective")
"""Activation kinds by code, as stored in ``FSNBatch.es_kind``."""
THRESHOLD, BELOW_THRESHOLD, SELECTIVE = range(3)
ACTIONS = ("buy", "hold", "quit")
"""Decision codes 0, 1, 2 (the order of the FC neurons B, L, Q)."""
NEURONS = ES_NEURONS + DECISIONS + JUDGEMENTS + VERDICTS
"""Every named neuron reported by ``activations``."""

# ---------------------------------------------------------------------------------------------
# The designed weights (spec auction.md §4.1, §5.2–§5.4). δ is the small "seed" weight that
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
    # ST peaks at the preferred sub-type (½, ½, ½): (st1 + st2 + st3)/3 − ½ = 0 there.
    "ST": ({"st1": 1 / 3, "st2": 1 / 3, "st3": 1 / 3}, -0.5),
}
"""Per ES neuron: the designed input weights (every other input gets δ) and the bias."""
SENSOR_ACTIVATIONS: dict[str, dict[str, float | str]] = {
    "PG": {"kind": "threshold", "a": 20.0, "c": 1.0, "negative_slope": 0.01},  # p/b > 1: fires
    "SZ": {"kind": "threshold", "a": 5.0, "c": 1.0, "negative_slope": 0.8},  # bigger than 1
    "LSR": {"kind": "threshold", "a": 1.0, "c": 0.5, "negative_slope": 0.01},  # f above ½
    "ST": {"kind": "selective", "epsilon": SELECTIVE_EPSILON},  # exactly the preferred type
}
"""Per ES neuron: its activation and parameters (spec §5.2; ST's ε as it runs, 1e-4)."""
DECISION_DESIGN: dict[str, tuple[dict[str, float], float]] = {
    # buy: cheap (−PG), big (SZ), others buying (LSR), my sub-type (ST); base intent 1.
    "B": ({"PG": -1.0, "SZ": 1.0, "LSR": 1.0, "ST": 1.0}, 1.0),
    # hold: price somewhat high (0.8 PG) unless the fish is big (−SZ); bias + hold_bias.
    "L": ({"PG": 0.8, "SZ": -1.0, "LSR": 0.0, "ST": 0.0}, 0.0),
    # quit: price far too high (2 PG overtakes B as PG saturates); bias −0.5 + quit_bias.
    "Q": ({"PG": 2.0, "SZ": 0.0, "LSR": 0.0, "ST": 0.0}, -0.5),
}
"""Per FC neuron: weights from PG, SZ, LSR, ST and the base bias (spec §4.1)."""
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
"""Per PFC verdict neuron: weights from tanh([PGL, BC, FQ]) and the bias (spec §5.4)."""
HOLD_BIAS_RANGE = (-0.5, 0.5)
"""Honest patrons add hold_bias ~ U(−0.5, 0.5) to L (spec §4.1)."""
QUIT_BIAS_RANGE = (0.0, 0.5)
"""Honest patrons add quit_bias ~ U(0, 0.5) to Q (spec §4.1)."""
FINE_TUNE_EPOCHS = (0, 2)
"""Honest fine-tuning epochs ~ randint{0, 1, 2} (spec §4.3; 0 = no fine-tuning)."""
FINE_TUNE_BATCH = (4, 15)
"""Honest fine-tuning batch size ~ randint{4..15} (spec §4.3)."""
FINE_TUNE_LR = (1e-7, 1e-4)
"""Honest SGD learning rate ~ U(1e−7, 1e−4) (spec §4.3)."""
SABOTEUR_HOLD_BIAS = 5.0
"""The saboteur's hold bias: L ≥ 5 − 0.8 − 1 > 3 whatever the input, above B and Q."""
SABOTEUR_BUY_BIAS = -1.0
"""The saboteur's buy bias; its buy weights are all zero, so B = −1 always (inert)."""
# ---------------------------------------------------------------------------------------------

_PARAMETERS = (
    "es_weight",
    "es_bias",
    "fc_weight",
    "fc_bias",
    "judgement_weight",
    "judgement_bias",
    "verdict_weight",
    "verdict_bias",
)
_PFC_PARAMETERS = frozenset(
    ("judgement_weight", "judgement_bias", "verdict_weight", "verdict_bias")
)


@dataclass
class FSNBatch:
    """Parameters of P Fish Sale Negotiators stacked on a leading patron axis (P may be 1).

    Trainable (SRD) parameters: ``es_weight`` (P,4,8) and ``es_bias`` (P,4) of the external
    sensor (rows PG, SZ, LSR, ST; columns the inputs in ``INPUTS`` order), ``fc_weight`` (P,3,4)
    and ``fc_bias`` (P,3) of the decision (rows B, L, Q), ``judgement_weight`` (P,3,7) and
    ``judgement_bias`` (P,3) of the PFC judgements (rows PGL, BC, FQ; columns PG..Q), and
    ``verdict_weight`` (P,2,3), ``verdict_bias`` (P,2) (rows T, F).

    Fixed per patron: the ES activation ``es_kind`` (P,4) (codes of ``ACTIVATION_KINDS``) with
    its parameters ``es_a``, ``es_c``, ``es_slope``, ``es_epsilon`` (P,4) (unused ones hold
    harmless placeholders), the augmentation ``copies`` (P,), ``noise_std`` (P,),
    ``noise_mask`` (P,8) (1 on jittered inputs), the fine-tuning ``epochs`` (P,),
    ``batch_size`` (P,), ``learning_rate`` (P,), ``pfc_trainable`` (P,) and the manifests'
    ``participants`` and ``descriptions``.
    """

    es_weight: Tensor
    es_bias: Tensor
    fc_weight: Tensor
    fc_bias: Tensor
    judgement_weight: Tensor
    judgement_bias: Tensor
    verdict_weight: Tensor
    verdict_bias: Tensor
    es_kind: Tensor
    es_a: Tensor
    es_c: Tensor
    es_slope: Tensor
    es_epsilon: Tensor
    copies: Tensor
    noise_std: Tensor
    noise_mask: Tensor
    epochs: Tensor
    batch_size: Tensor
    learning_rate: Tensor
    pfc_trainable: Tensor
    participants: list[str]
    descriptions: list[str]

    @property
    def n_patrons(self) -> int:
        """P."""
        return int(self.es_weight.shape[0])

    @property
    def max_copies(self) -> int:
        """The largest D_ic of the batch (the copy axis of noise tensors)."""
        return int(self.copies.max())

    @property
    def dtype(self) -> torch.dtype:
        return self.es_weight.dtype

    @functools.cached_property
    def activation_groups(self) -> list[tuple[int | None, slice]]:
        """Runs of ES neurons sharing one activation kind in every patron (see ``_sensor``)."""
        return _kind_groups(self.es_kind)

    def parameters(self) -> dict[str, Tensor]:
        """The trainable tensors by name."""
        return {name: getattr(self, name) for name in _PARAMETERS}

    def with_parameters(self, params: dict[str, Tensor]) -> FSNBatch:
        """A copy of the batch with some trainable tensors replaced."""
        changes: dict[str, Any] = dict(params)
        return dataclasses.replace(self, **changes)

    def select(self, index: Sequence[int] | Tensor | np.ndarray | slice) -> FSNBatch:
        """The sub-batch of the patrons at ``index`` (in that order; a slice gives views)."""
        if isinstance(index, slice):
            sliced = {f.name: getattr(self, f.name)[index] for f in dataclasses.fields(self)}
            return FSNBatch(**sliced)
        idx = torch.as_tensor(index, dtype=torch.long)
        fields: dict[str, object] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Tensor):
                fields[f.name] = value.index_select(0, idx)
            else:
                fields[f.name] = [value[i] for i in idx.tolist()]
        return FSNBatch(**fields)  # type: ignore[arg-type]


_INPUT_VALUES = operator.attrgetter(*INPUTS)
_ES_VALUES = operator.attrgetter(*ES_NEURONS)
_DECISION_VALUES = operator.attrgetter(*DECISIONS)
_SOURCE_VALUES = operator.attrgetter(*PFC_SOURCES)
_JUDGEMENT_VALUES = operator.attrgetter(*JUDGEMENTS)
_VERDICT_VALUES = operator.attrgetter(*VERDICTS)
_PLACEHOLDER_SHAPE = (1.0, 0.0, 0.0)
"""a, c, negative_slope stored for a selective neuron (unused)."""
_PLACEHOLDER_EPSILON = 1.0
"""ε stored for a threshold neuron (unused; any positive number avoids 0/0)."""

_Numbers = tuple[float, ...]
_Memo = Callable[[Any, Callable[[Any], _Numbers]], _Numbers]
"""``memo(obj, read)``: ``read(obj)``, read once per distinct object (by identity)."""


def _activation_numbers(
    act: ThresholdActivation | BelowThresholdActivation | SelectiveActivation,
) -> _Numbers:
    """(kind code, a, c, negative_slope, ε) of one ES activation."""
    if act.kind == "selective":  # not isinstance: slow on pydantic models (ABC checks)
        return (SELECTIVE, *_PLACEHOLDER_SHAPE, act.epsilon)
    return (
        ACTIVATION_KINDS.index(act.kind),
        act.a,
        act.c,
        act.negative_slope,
        _PLACEHOLDER_EPSILON,
    )


def _sensor_numbers(s: Any, memo: _Memo) -> _Numbers:
    """One ES neuron: weights, bias, kind code, a, c, slope, ε."""
    return (*memo(s.weights, _INPUT_VALUES), s.bias, *memo(s.activation, _activation_numbers))


def _decision_numbers(n: Any, memo: _Memo) -> _Numbers:
    """One FC neuron: weights, bias."""
    return (*memo(n.weights, _ES_VALUES), n.bias)


def _pfc_numbers(p: Any, memo: _Memo) -> _Numbers:
    """The PFC: judgement weights and biases, verdict weights and biases, trainable."""
    neurons = [(j, _SOURCE_VALUES) for j in _JUDGEMENT_VALUES(p.judgement)]
    neurons += [(v, _JUDGEMENT_VALUES) for v in _VERDICT_VALUES(p.verdict)]
    weights = ((*memo(n.weights, read), n.bias) for n, read in neurons)
    return (*itertools.chain.from_iterable(weights), float(p.trainable))


def _augmentation_numbers(a: Any, memo: _Memo) -> _Numbers:
    """Copies, σ, the noise mask."""
    off = a.noiseless_inputs
    return (a.copies, a.noise_std, *(0.0 if name in off else 1.0 for name in INPUTS))


def _tuning_numbers(f: Any, memo: _Memo) -> _Numbers:
    """Epochs, batch size, learning rate."""
    return (f.epochs, f.batch_size, f.learning_rate)


_READERS = (
    *[_sensor_numbers] * len(ES_NEURONS),
    *[_decision_numbers] * len(DECISIONS),
    _pfc_numbers,
    _augmentation_numbers,
    _tuning_numbers,
)
"""The readers of a manifest's parts, in table order: ES neurons, FC neurons, PFC,
augmentation, fine-tuning (see ``_COLUMN_BLOCKS``)."""


def from_manifests(manifests: Sequence[Manifest], dtype: torch.dtype = torch.float64) -> FSNBatch:
    """Stack the manifests' numbers into one batch (float64 keeps them exact)."""
    if not manifests:
        raise ValueError("at least one manifest is needed")
    # One row of numbers per manifest, read part by part (ES neurons, FC neurons, PFC,
    # augmentation, fine-tuning). Factory-made manifests share their frozen sub-models: each
    # distinct part is read once.
    parts = [
        part
        for m in manifests
        for part in (
            *_ES_VALUES(m.external_sensor),
            *_DECISION_VALUES(m.decision),
            m.pfc,
            m.augmentation,
            m.fine_tuning,
        )
    ]
    numbers: dict[int, _Numbers] = {}

    def memo(obj: Any, read: Callable[[Any], _Numbers]) -> _Numbers:
        key = id(obj)
        found = numbers.get(key)
        if found is None:
            found = numbers[key] = read(obj)
        return found

    keys = list(map(id, parts))
    for key, part, read in zip(keys, parts, _READERS * len(manifests), strict=True):
        if key not in numbers:
            numbers[key] = read(part, memo)
    flat = itertools.chain.from_iterable(map(numbers.__getitem__, keys))
    width = sum(_COLUMN_BLOCKS)
    table = np.fromiter(flat, np.float64, count=len(manifests) * width).reshape(-1, width)
    P, n_in = len(manifests), len(INPUTS)
    blocks = iter(np.split(table, np.cumsum(_COLUMN_BLOCKS)[:-1], axis=1))
    es, fc_, judgement, verdict_, trainable, copies, std, mask, epochs, size, lr = blocks
    es = es.reshape(P, len(ES_NEURONS), -1)
    fc_ = fc_.reshape(P, len(DECISIONS), -1)
    judgement = judgement.reshape(P, len(JUDGEMENTS), -1)
    verdict_ = verdict_.reshape(P, len(VERDICTS), -1)

    def real(values: np.ndarray) -> Tensor:
        return torch.tensor(values, dtype=dtype)

    def integer(values: np.ndarray) -> Tensor:
        return torch.tensor(values, dtype=torch.long)

    return FSNBatch(
        es_weight=real(es[:, :, :n_in]),
        es_bias=real(es[:, :, n_in]),
        fc_weight=real(fc_[:, :, :-1]),
        fc_bias=real(fc_[:, :, -1]),
        judgement_weight=real(judgement[:, :, :-1]),
        judgement_bias=real(judgement[:, :, -1]),
        verdict_weight=real(verdict_[:, :, :-1]),
        verdict_bias=real(verdict_[:, :, -1]),
        es_kind=integer(es[:, :, n_in + 1]),
        es_a=real(es[:, :, n_in + 2]),
        es_c=real(es[:, :, n_in + 3]),
        es_slope=real(es[:, :, n_in + 4]),
        es_epsilon=real(es[:, :, n_in + 5]),
        copies=integer(copies[:, 0]),
        noise_std=real(std[:, 0]),
        noise_mask=real(mask),
        epochs=integer(epochs[:, 0]),
        batch_size=integer(size[:, 0]),
        learning_rate=real(lr[:, 0]),
        pfc_trainable=torch.tensor(trainable[:, 0] != 0.0),
        participants=[m.participant for m in manifests],
        descriptions=[m.description for m in manifests],
    )


_COLUMN_BLOCKS = (
    len(ES_NEURONS) * (len(INPUTS) + 1 + 5),  # ES: weights, bias, kind, a, c, slope, ε
    len(DECISIONS) * (len(ES_NEURONS) + 1),  # FC: weights, bias
    len(JUDGEMENTS) * (len(PFC_SOURCES) + 1),  # judgements: weights, bias
    len(VERDICTS) * (len(JUDGEMENTS) + 1),  # verdicts: weights, bias
    1,  # pfc.trainable
    1,  # augmentation copies
    1,  # noise σ
    len(INPUTS),  # noise mask
    1,  # fine-tuning epochs
    1,  # batch size
    1,  # learning rate
)
"""Widths of the column blocks of the flat per-manifest rows in ``from_manifests``."""


def _named(values: list[float], names: Sequence[str]) -> dict[str, float]:
    return dict(zip(names, values, strict=True))


def to_manifest(batch: FSNBatch, index: int, participant: str | None = None) -> Manifest:
    """Patron ``index`` of the batch as a manifest (exact inverse of ``from_manifests`` in
    float64); ``participant`` overrides the stored name."""
    p = index
    es_w, es_b = batch.es_weight[p].tolist(), batch.es_bias[p].tolist()
    kinds = batch.es_kind[p].tolist()
    a, c = batch.es_a[p].tolist(), batch.es_c[p].tolist()
    slope, eps = batch.es_slope[p].tolist(), batch.es_epsilon[p].tolist()
    sensor = {}
    for n, name in enumerate(ES_NEURONS):
        kind = ACTIVATION_KINDS[kinds[n]]
        activation: dict[str, object] = {"kind": kind}
        if kind == "selective":
            activation["epsilon"] = eps[n]
        else:
            activation |= {"a": a[n], "c": c[n], "negative_slope": slope[n]}
        sensor[name] = {
            "weights": _named(es_w[n], INPUTS),
            "bias": es_b[n],
            "activation": activation,
        }

    def layer(
        weight: Tensor, bias: Tensor, rows: Sequence[str], cols: Sequence[str]
    ) -> dict[str, Any]:
        w, b = weight[p].tolist(), bias[p].tolist()
        return {r: {"weights": _named(w[i], cols), "bias": b[i]} for i, r in enumerate(rows)}

    mask = batch.noise_mask[p].tolist()
    data = {
        "participant": participant if participant is not None else batch.participants[p],
        "description": batch.descriptions[p],
        "augmentation": {
            "copies": int(batch.copies[p]),
            "noise_std": float(batch.noise_std[p]),
            "noiseless_inputs": [name for name, m in zip(INPUTS, mask, strict=True) if m == 0.0],
        },
        "external_sensor": sensor,
        "decision": layer(batch.fc_weight, batch.fc_bias, DECISIONS, ES_NEURONS),
        "pfc": {
            "judgement": layer(
                batch.judgement_weight, batch.judgement_bias, JUDGEMENTS, PFC_SOURCES
            ),
            "verdict": layer(batch.verdict_weight, batch.verdict_bias, VERDICTS, JUDGEMENTS),
            "trainable": bool(batch.pfc_trainable[p]),
        },
        "fine_tuning": {
            "epochs": int(batch.epochs[p]),
            "batch_size": int(batch.batch_size[p]),
            "learning_rate": float(batch.learning_rate[p]),
        },
    }
    return Manifest.model_validate(data)


def make_noise(batch: FSNBatch, n_rows: int, generator: torch.Generator) -> Tensor:
    """Augmentation noise (P, R, D, 8), D = the batch's largest D_ic: σ_p·N(0, 1) on copies
    1..D_ic(p)−1 and jittered inputs, exactly 0 on copy 0, on noiseless inputs and on copies a
    patron does not have."""
    normal = standard_normal((batch.n_patrons, n_rows, batch.max_copies), generator)
    return normal.to(batch.dtype) * noise_scale(batch)[:, None]


def standard_normal(
    shape: tuple[int, ...], generator: torch.Generator, out: Tensor | None = None
) -> Tensor:
    """N(0, 1) draws of shape (*shape, 8), made in float32: CPU float64 normals are several
    times slower and σ = 0.01 jitter needs no more precision. ``out``, if given, must be a
    contiguous float32 tensor of that shape (the draws are the same)."""
    return torch.randn((*shape, len(INPUTS)), generator=generator, dtype=torch.float32, out=out)


def noise_scale(batch: FSNBatch) -> Tensor:
    """(P, D, 8): σ_p on the jittered (copy, input) cells, 0 elsewhere."""
    d = torch.arange(batch.max_copies)
    copy_on = ((d >= 1) & (d[None, :] < batch.copies[:, None])).to(batch.dtype)  # (P, D)
    return batch.noise_std[:, None, None] * copy_on[:, :, None] * batch.noise_mask[:, None, :]


# The forward pass works neuron-major: tensors are (neuron, row, copy, patron), patron last, so
# every per-patron parameter broadcasts along the contiguous axis (several times faster on CPU
# than patron-major broadcasting). Public functions return (patron, row, ...) tensors.


def _per_patron(values: Tensor) -> Tensor:
    """(P, K) parameters → (K, 1, 1, P) for broadcasting over (K, R, D, P)."""
    return values.T.contiguous()[:, None, None, :]


def _sensor(batch: FSNBatch, x: Tensor, noise: Tensor | None) -> Tensor:
    """ES activations per copy, (4, R, D, P) (D = 1 when there is no noise)."""
    x = x.to(batch.dtype)
    equation = "rj,pkj->krp" if x.dim() == 2 else "prj,pkj->krp"
    clean = torch.einsum(equation, x, batch.es_weight) + batch.es_bias.T[:, None, :]
    clean = clean.contiguous()[:, :, None, :]  # (4, R, 1, P)
    groups = batch.activation_groups
    parts = [_activate(batch, kind, neurons, clean, noise) for kind, neurons in groups]
    return torch.cat(parts) if len(parts) > 1 else parts[0]


def _kind_groups(es_kind: Tensor) -> list[tuple[int | None, slice]]:
    """Runs of ES neurons that share one activation kind in every patron (the usual case:
    PG..LSR threshold, ST selective); one mixed group (kind None) otherwise."""
    uniform = bool((es_kind == es_kind[:1]).all())
    if not uniform:
        return [(None, slice(0, es_kind.shape[1]))]
    kinds = es_kind[0].tolist()
    groups: list[tuple[int | None, slice]] = []
    start = 0
    for n in range(1, len(kinds) + 1):
        if n == len(kinds) or kinds[n] != kinds[start]:
            groups.append((kinds[start], slice(start, n)))
            start = n
    return groups


def _activate(
    batch: FSNBatch, kind: int | None, neurons: slice, clean: Tensor, noise: Tensor | None
) -> Tensor:
    """The activations of the ES neurons ``neurons`` (all of one ``kind``; None = mixed)."""
    weight = batch.es_weight[:, neurons]
    a, c = _per_patron(batch.es_a[:, neurons]), _per_patron(batch.es_c[:, neurons])
    slope = _per_patron(batch.es_slope[:, neurons])
    eps = _per_patron(batch.es_epsilon[:, neurons])

    def jitter(w: Tensor) -> Tensor:  # W·ε per copy: the linear map of the noise
        assert noise is not None
        return torch.einsum("prdj,pkj->krdp", noise, w).contiguous()

    if kind == SELECTIVE:
        pre = clean[neurons] if noise is None else clean[neurons] + jitter(weight)
        return eps / (eps + pre * pre)
    if kind is not None:
        # a·(W·(x + ε) + b − c) = a·(W·x + b − c) + (a·W)·ε
        z = (clean[neurons] - c) * a
        if noise is not None:
            z = z + jitter(weight * batch.es_a[:, neurons, None])
        # leaky_relu(z, ns) = max(z, ns·z) because 0 ≤ ns ≤ 1 (the manifest's range).
        fired = torch.tanh(torch.maximum(z, slope * z))
        return fired if kind == THRESHOLD else 1.0 - fired  # BT = tanh(−lrelu) + 1 = 1 − T
    pre = clean[neurons] if noise is None else clean[neurons] + jitter(weight)
    z = (pre - c) * a
    fired = torch.tanh(torch.maximum(z, slope * z))
    codes = batch.es_kind[:, neurons]
    below = _per_patron((codes == BELOW_THRESHOLD).to(batch.dtype))
    chosen = _per_patron((codes == SELECTIVE).to(batch.dtype))
    out = fired + below * (1.0 - 2.0 * fired)
    return out + chosen * (eps / (eps + pre * pre) - out)


def _linear(weight: Tensor, bias: Tensor, inputs: Tensor) -> Tensor:
    """A per-patron linear layer on (K_in, R, D, P) → (K_out, R, D, P)."""
    return torch.einsum("krdp,pjk->jrdp", inputs, weight).contiguous() + _per_patron(bias)


def _copy_mean(batch: FSNBatch, values: Tensor) -> Tensor:
    """Average (K, R, D, P) over each patron's own copies → (K, R, P)."""
    n_copies = values.shape[2]
    if n_copies == 1:
        return values[:, :, 0]
    on = (torch.arange(n_copies)[:, None] < batch.copies[None, :]).to(batch.dtype)  # (D, P)
    return (values * (on / on.sum(dim=0))).sum(dim=2)


def _pfc(batch: FSNBatch, sensor: Tensor, decision: Tensor) -> tuple[Tensor, Tensor]:
    """Judgements [PGL, BC, FQ] (before their tanh) and verdicts [T, F], per copy."""
    sources = torch.cat((sensor, decision), dim=0)
    e = torch.exp(sources - sources.detach().amax(dim=0, keepdim=True))
    judgement = _linear(batch.judgement_weight, batch.judgement_bias, e / e.sum(dim=0))
    verdict = _linear(batch.verdict_weight, batch.verdict_bias, torch.tanh(judgement))
    return judgement, verdict


def _patron_major(values: Tensor) -> Tensor:
    """(K, R, P) → (P, R, K)."""
    return values.permute(2, 1, 0).contiguous()


def decision_logits(batch: FSNBatch, x: Tensor, noise: Tensor | None = None) -> Tensor:
    """[B, L, Q] averaged over the copies, (P, R, 3); ``x`` is (R, 8) shared by every patron or
    (P, R, 8); ``noise`` (P, R, D, 8) from ``make_noise``, None = every copy clean."""
    # The FC is linear: averaging the sensor over copies first gives the same mean, cheaper.
    mean_sensor = _patron_major(_copy_mean(batch, _sensor(batch, x, noise)))  # (P, R, 4)
    return torch.einsum("prk,pjk->prj", mean_sensor, batch.fc_weight) + batch.fc_bias[:, None, :]


def decide(batch: FSNBatch, x: Tensor, noise: Tensor | None = None) -> Tensor:
    """Greedy decisions (P, R) int64: 0 buy, 1 hold, 2 quit (ties → the lowest index)."""
    return decision_logits(batch, x, noise).argmax(dim=-1)


def self_reward(batch: FSNBatch, x: Tensor, noise: Tensor | None) -> Tensor:
    """The PFC's verdicts [T, F] averaged over the copies, (P, R, 2)."""
    sensor = _sensor(batch, x, noise)
    _, verdict = _pfc(batch, sensor, _linear(batch.fc_weight, batch.fc_bias, sensor))
    return _patron_major(_copy_mean(batch, verdict))


def activations(batch: FSNBatch, x: Tensor, noise: Tensor | None = None) -> dict[str, Tensor]:
    """Every named neuron averaged over the copies, (P, R) each: PG, SZ, LSR, ST (after their
    activations), B, L, Q (FC outputs), PGL, BC, FQ (judgements before their tanh), T, F."""
    sensor = _sensor(batch, x, noise)
    decision = _linear(batch.fc_weight, batch.fc_bias, sensor)
    judgement, verdict = _pfc(batch, sensor, decision)
    stacked = _copy_mean(batch, torch.cat((sensor, decision, judgement, verdict), dim=0))
    return {name: stacked[i].T.contiguous() for i, name in enumerate(NEURONS)}


# --- SRD fine-tuning --------------------------------------------------------------------------


@dataclass
class FineTuneDraws:
    """The random numbers of one fine-tuning round, drawn for every patron of a batch.

    ``order`` (P, E, R): patron p's shuffle of the R rows in epoch e; ``normal``
    (P, E, R, D, 8): float32 N(0, 1) draws that ``scale`` (P, D, 8) (``noise_scale``) turns
    into ``noise``, the augmentation noise row r receives when patron p visits it in epoch e.
    E is the largest epoch count of the batch. A per-patron loop that slices these sees the
    same numbers.
    """

    order: Tensor
    normal: Tensor
    scale: Tensor

    @functools.cached_property
    def noise(self) -> Tensor:
        """(P, E, R, D, 8) (``fine_tune`` itself scales only the rows it visits)."""
        return self.normal.to(self.scale.dtype) * self.scale[:, None, None]


def draw_fine_tune(batch: FSNBatch, n_rows: int, generator: torch.Generator) -> FineTuneDraws:
    """Draw one round's shuffles and noise (empty when no patron has epochs)."""
    return draw_fine_tune_blocks(batch, n_rows, [(batch.n_patrons, generator)])


def draw_fine_tune_blocks(
    batch: FSNBatch, n_rows: int, blocks: Sequence[tuple[int, torch.Generator]]
) -> FineTuneDraws:
    """One round's draws for consecutive blocks of patrons, given as (size, generator): each
    block draws what ``draw_fine_tune`` would draw for it alone (its epochs and copies are
    padded to the batch's: a padded epoch is never visited, a padded copy has no noise)."""
    P, E, D = batch.n_patrons, int(batch.epochs.max()), batch.max_copies
    bounds = list(itertools.pairwise(np.cumsum([0, *(size for size, _ in blocks)]).tolist()))
    order = torch.empty((P, E, n_rows), dtype=torch.long)
    normal = torch.empty((P, E, n_rows, D, len(INPUTS)), dtype=torch.float32)
    for (_, generator), (start, stop) in zip(blocks, bounds, strict=True):
        epochs, copies = int(batch.epochs[start:stop].max()), int(batch.copies[start:stop].max())
        keys = torch.rand((stop - start, epochs, n_rows), generator=generator, dtype=torch.float64)
        order[start:stop, :epochs] = keys.argsort(dim=-1)
        order[start:stop, epochs:] = torch.arange(n_rows)
        shape = (stop - start, epochs, n_rows, copies)
        if (epochs, copies) == (E, D):
            standard_normal(shape, generator, out=normal[start:stop])
        else:
            normal[start:stop, :epochs, :, :copies] = standard_normal(shape, generator)
            normal[start:stop, epochs:] = 0.0
            normal[start:stop, :epochs, :, copies:] = 0.0
    return FineTuneDraws(order=order, normal=normal, scale=noise_scale(batch))


SEED_BITS = 53
"""Derived seeds have 53 bits: exact as JSON numbers in any language (IEEE doubles)."""
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX = (np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB))


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64's output function of x + golden ratio (uint64, wrapping), element-wise."""
    z = x + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _MIX[0]
    z = (z ^ (z >> np.uint64(27))) * _MIX[1]
    return z ^ (z >> np.uint64(31))


def derive_seeds(parent: int | np.ndarray, child: int | Sequence[int] | np.ndarray) -> np.ndarray:
    """Seeds derived from (parent, child) pairs, element-wise (uint64 array, < 2**SEED_BITS):
    splitmix64(splitmix64(parent) XOR child) keeping its low SEED_BITS bits. Cheap and
    vectorised, so a round can derive one seed per patron without a Python loop."""
    with np.errstate(over="ignore"):
        mixed = _splitmix64(np.asarray(parent, dtype=np.uint64)) ^ np.asarray(child, np.uint64)
        return np.atleast_1d(_splitmix64(mixed) & np.uint64((1 << SEED_BITS) - 1))


def draw_fine_tune_seeded(
    batch: FSNBatch, n_rows: int, shuffle_seeds: np.ndarray, noise_seeds: np.ndarray
) -> FineTuneDraws:
    """One round's draws with every patron's own generators: patron p's shuffle keys (its
    epochs × R uniforms, argsorted per epoch) from a torch generator seeded with
    ``shuffle_seeds[p]``, its N(0, 1) augmentation draws (epochs × R × its D_ic × 8) from one
    seeded with ``noise_seeds[p]``. A patron's draws depend on its own settings and seeds
    only, so it draws the same numbers alone (a remote agent) as in any batch. Patrons
    without epochs draw nothing (they are never visited)."""
    P, E, D = batch.n_patrons, int(batch.epochs.max()), batch.max_copies
    keys = torch.zeros((P, E, n_rows), dtype=torch.float64)
    normal = torch.empty((P, E, n_rows, D, len(INPUTS)), dtype=torch.float32)
    generator = torch.Generator()
    epochs, copies = batch.epochs.tolist(), batch.copies.tolist()
    shuffle, noise = shuffle_seeds.tolist(), noise_seeds.tolist()
    for p in range(P):
        e, c = epochs[p], copies[p]
        if e == 0:
            continue
        generator.manual_seed(shuffle[p])
        torch.rand((e, n_rows), generator=generator, dtype=torch.float64, out=keys[p, :e])
        generator.manual_seed(noise[p])
        if (e, c) == (E, D):
            standard_normal((e, n_rows, c), generator, out=normal[p])
        else:  # padded epochs are never visited; padded copies must hold finite zeros
            normal[p, :e, :, :c] = standard_normal((e, n_rows, c), generator)
            normal[p, :e, :, c:] = 0.0
    return FineTuneDraws(order=keys.argsort(dim=-1), normal=normal, scale=noise_scale(batch))


def _flat_parameters(batch: FSNBatch) -> Tensor:
    """The trainable tensors side by side, (P, N_θ), in ``_PARAMETERS`` order."""
    P = batch.n_patrons
    return torch.cat([t.reshape(P, -1) for t in batch.parameters().values()], dim=1)


def _unflatten(batch: FSNBatch, flat: Tensor) -> dict[str, Tensor]:
    """The inverse of ``_flat_parameters``."""
    shapes = [t.shape for t in batch.parameters().values()]
    widths = [int(np.prod(shape[1:])) for shape in shapes]
    parts = torch.split(flat, widths, dim=1)
    return {
        name: part.reshape(shape).clone()
        for name, part, shape in zip(_PARAMETERS, parts, shapes, strict=True)
    }


_LAYER_SHAPES = (
    (len(ES_NEURONS), len(INPUTS)),
    (len(ES_NEURONS), 1),
    (len(DECISIONS), len(ES_NEURONS)),
    (len(DECISIONS), 1),
    (len(JUDGEMENTS), len(PFC_SOURCES)),
    (len(JUDGEMENTS), 1),
    (len(VERDICTS), len(JUDGEMENTS)),
    (len(VERDICTS), 1),
)
"""Per patron, the trainable tensors of ``_PARAMETERS`` as matrices (biases as columns)."""


def _layer_views(theta: Tensor) -> list[Tensor]:
    """Views (k, out, in) and (k, out, 1) of the flat parameters ``theta`` (k, N_θ)."""
    parts = torch.split(theta, [rows * cols for rows, cols in _LAYER_SHAPES], dim=1)
    return [p.view(-1, *shape) for p, shape in zip(parts, _LAYER_SHAPES, strict=True)]


def _threshold_and_slope(
    u: Tensor, numbers: dict[str, Tensor], out: Tensor | None = None, d_out: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """T(u) = tanh(lrelu(a·(u − c), ns)) and dT/du (into ``out`` and ``d_out`` if given)."""
    z = (u - numbers["c"]) * numbers["a"]
    fired = torch.tanh(torch.maximum(z, numbers["slope"] * z), out=out)
    # a·d max(z, ns·z)/dz: a above 0, ns·a below, their mean at a tie (as autograd).
    bend = torch.addcmul(numbers["bend_mid"], torch.sign(z), numbers["bend_half"])
    return fired, torch.mul(1.0 - fired * fired, bend, out=d_out)


def _selective_and_slope(
    u: Tensor, numbers: dict[str, Tensor], out: Tensor | None = None, d_out: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """S(u) = ε/(ε + u²) and dS/du = −2u·S²/ε (into ``out`` and ``d_out`` if given)."""
    eps = numbers["epsilon"]
    chosen = torch.div(eps, eps + u * u, out=out)
    return chosen, torch.mul(chosen * chosen, u * numbers["minus_two_over_epsilon"], out=d_out)


def _sensor_and_slope(
    groups: list[tuple[int | None, slice]],
    numbers: dict[str, Tensor],
    pre: Tensor,
    sensor: Tensor,
    slope: Tensor,
) -> None:
    """ES activations of the pre-activations ``pre`` (k, 4, M) into ``sensor`` and their
    derivatives into ``slope``; ``numbers`` (see ``_activation_table``) are (k, 4, 1)."""
    for kind, neurons in groups:
        u, out, d_out = pre[:, neurons], sensor[:, neurons], slope[:, neurons]
        mine = {name: value[:, neurons] for name, value in numbers.items()}
        if kind == SELECTIVE:
            _selective_and_slope(u, mine, out, d_out)
        elif kind is not None:
            _threshold_and_slope(u, mine, out, d_out)
            if kind == BELOW_THRESHOLD:  # BT = 1 − T
                out.neg_().add_(1.0)
                d_out.neg_()
        else:
            fired, d_fired = _threshold_and_slope(u, mine)
            chosen, d_chosen = _selective_and_slope(u, mine)
            below, selective = mine["kind"] == BELOW_THRESHOLD, mine["kind"] == SELECTIVE
            out.copy_(torch.where(selective, chosen, torch.where(below, 1.0 - fired, fired)))
            d_out.copy_(torch.where(selective, d_chosen, torch.where(below, -d_fired, d_fired)))


def _activation_table(batch: FSNBatch, patrons: Tensor) -> dict[str, Tensor]:
    """The ES activation numbers of ``patrons`` as (k, 4, 1) columns, with the constants of
    their derivatives."""
    a, ns, eps = batch.es_a[patrons], batch.es_slope[patrons], batch.es_epsilon[patrons]
    table = {
        "kind": batch.es_kind[patrons],
        "a": a,
        "c": batch.es_c[patrons],
        "slope": ns,
        "epsilon": eps,
        "bend_mid": 0.5 * (a + ns * a),
        "bend_half": 0.5 * (a - ns * a),
        "minus_two_over_epsilon": -2.0 / eps,
    }
    return {name: value[:, :, None].contiguous() for name, value in table.items()}


def _band_gradient(
    groups: list[tuple[int | None, slice]],
    theta: Tensor,
    numbers: dict[str, Tensor],
    xe: Tensor,
    copy_weight: Tensor,
    weight: Tensor,
) -> Tensor:
    """∇θ of Σ_rows weight·CEL([T, F], argmax [T, F]) for k patrons, (k, N_θ): ``theta``
    (k, N_θ) their flat parameters, ``xe`` (k, B, D, 8) their batch rows plus each copy's
    noise, ``copy_weight`` (k, D) (1/D_ic on a patron's copies), ``weight`` (k, B) (1/rows
    in the batch, 0 on padding). The forward pass of ``self_reward`` and its backward written
    out, each layer one batch of per-patron matrix products over the B·D (row, copy) columns."""
    k, B, D, n_in = xe.shape
    n_es = len(ES_NEURONS)
    es_w, es_b, fc_w, fc_b, j_w, j_b, v_w, v_b = _layer_views(theta)
    inputs = xe.view(k, B * D, n_in)
    # Forward: ES → FC → softmax of the 7 sources → judgements → tanh → verdicts.
    pre = torch.baddbmm(es_b, es_w, inputs.transpose(1, 2))  # (k, 4, B·D)
    sources = theta.new_empty((k, len(PFC_SOURCES), B * D))
    sensor, slope = sources[:, :n_es], torch.empty_like(pre)
    _sensor_and_slope(groups, numbers, pre, sensor, slope)
    sources[:, n_es:] = torch.baddbmm(fc_b, fc_w, sensor)
    soft = torch.softmax(sources, dim=1)
    judged = torch.tanh(torch.baddbmm(j_b, j_w, soft))
    # The verdicts are linear in the judgements, so their mean over the copies (Σ_d w_d = 1)
    # is the verdict of the copies' mean judgement: (k, 3, B) → [T, F] (k, 2, B).
    n_j = len(JUDGEMENTS)
    judged_mean = torch.bmm(judged.view(k, n_j * B, D), copy_weight[:, :, None]).view(k, n_j, B)
    mean = torch.baddbmm(v_b, v_w, judged_mean)
    # Backward: d CEL / d logits = softmax − one-hot(argmax), times the row's weight; the
    # argmax of [T, F] is T unless F is larger.
    true = mean[:, :1] >= mean[:, 1:]
    chosen = torch.cat((true, ~true), dim=1).to(mean.dtype)
    g_mean = (torch.softmax(mean, dim=1) - chosen) * weight[:, None]
    g_judged_mean = torch.bmm(v_w.transpose(1, 2), g_mean)  # (k, 3, B)
    g_judged = (1.0 - judged * judged).view(k, n_j, B, D)
    g_judged = (g_judged * g_judged_mean[..., None] * copy_weight[:, None, None, :]).view(
        k, n_j, B * D
    )
    g_soft = torch.bmm(j_w.transpose(1, 2), g_judged)
    # soft·(g_soft − Σ soft·g_soft), fused.
    g_sources = torch._softmax_backward_data(g_soft, soft, 1, soft.dtype)
    g_decision = g_sources[:, n_es:]
    g_pre = torch.baddbmm(g_sources[:, :n_es], fc_w.transpose(1, 2), g_decision) * slope
    grads = (
        torch.bmm(g_pre, inputs),
        g_pre.sum(-1),
        torch.bmm(g_decision, sensor.transpose(1, 2)),
        g_decision.sum(-1),
        torch.bmm(g_judged, soft.transpose(1, 2)),
        g_judged.sum(-1),
        torch.bmm(g_mean, judged_mean.transpose(1, 2)),
        g_mean.sum(-1),
    )
    return torch.cat([g.reshape(k, -1) for g in grads], dim=1)


_STEP_COST = 2000
"""The fixed cost of one SGD step of a band (≈ 60 tensor operations), in (row, copy)
evaluations: patrons of nearby batch sizes share a band while the padding costs less."""


def _bands(size: Tensor, steps: Tensor, copies: Tensor) -> list[Tensor]:
    """The patrons that take SGD steps, in bands of nearby batch sizes (padded to the band's
    largest); each band sorted by steps, most first, so the patrons still stepping at any step
    are a prefix. The bands minimise Σ steps·``_STEP_COST`` + padded (row, copy) evaluations."""
    moving = torch.nonzero(steps > 0).flatten()
    by_size: dict[int, list[int]] = {}
    for patron, b in zip(moving.tolist(), size[moving].tolist(), strict=True):
        by_size.setdefault(b, []).append(patron)
    sizes = sorted(by_size)
    n_steps, n_copies = steps.tolist(), copies.tolist()
    most = [max(n_steps[p] for p in by_size[b]) for b in sizes]
    total = [sum(n_steps[p] for p in by_size[b]) for b in sizes]
    widest = [max(n_copies[p] for p in by_size[b]) for b in sizes]
    # best[j]: (cost, start of the last band) of the first j sizes.
    best = [(0.0, 0)]
    for j in range(1, len(sizes) + 1):
        options, band_steps, band_copies, band_total = [], 0, 0, 0
        for i in range(j - 1, -1, -1):  # the last band holds sizes i..j-1
            band_steps, band_copies = max(band_steps, most[i]), max(band_copies, widest[i])
            band_total += total[i]
            evaluations = sizes[j - 1] * band_copies * band_total
            options.append((best[i][0] + band_steps * _STEP_COST + evaluations, i))
        best.append(min(options))
    bands = []
    j = len(sizes)
    while j > 0:
        i = best[j][1]
        members = torch.tensor([p for b in sizes[i:j] for p in by_size[b]])
        bands.append(members[torch.argsort(steps[members], descending=True, stable=True)])
        j = i
    return bands


def _tune_band(
    batch: FSNBatch,
    band: Tensor,
    steps: Tensor,
    theta: Tensor,
    rate: Tensor,
    x: Tensor,
    dataset: Tensor,
    draws: FineTuneDraws,
) -> Tensor:
    """SGD of the patrons ``band`` (sorted by ``steps``, most first) from their flat parameters
    ``theta`` (updated in place and returned) with per-column learning rates ``rate``; patron p
    learns from the rows ``x[dataset[p]]``."""
    n, R = len(band), x.shape[-2]
    _, E, _, all_copies, n_in = draws.normal.shape
    size = batch.batch_size[band].clamp(max=R)
    per_epoch = torch.div(R + size - 1, size, rounding_mode="floor")
    B, D = int(size.max()), int(batch.copies[band].max())
    # Each patron's shuffled rows, epoch after epoch; its step s takes batch s of them. The
    # (step, patron, slot) tables: the row visited (its draw and its dataset row) and its
    # weight, 1/rows in the batch (0 on the padding slots past the batch's last row).
    S = int(steps[0])
    step = torch.arange(S)[:, None, None]
    epoch = torch.div(step, per_epoch[:, None], rounding_mode="floor")  # (S, n, 1)
    start = (step - epoch * per_epoch[:, None]) * size[:, None]
    count = torch.minimum(size[:, None], R - start)
    slot = torch.arange(B)
    position = epoch * R + start + torch.minimum(slot, count - 1)  # (S, n, B)
    position = position.clamp(max=E * R - 1)  # past a patron's last step: never used
    sequence = draws.order[band].reshape(n, 1, E * R).expand(n, S, E * R)
    row = sequence.gather(2, position.transpose(0, 1)).transpose(0, 1)
    visit = (band[:, None] * E + epoch) * R + row
    at = dataset[band, None] * R + row
    weight = (slot < count) / count.to(batch.dtype)
    stepping = (steps > step[:, 0, 0, None]).sum(dim=1).tolist()  # patrons still stepping
    normal = draws.normal.reshape(-1, all_copies, n_in)
    scale = draws.scale[band, None, :D]
    rows = x.to(batch.dtype).reshape(-1, n_in)
    on = (torch.arange(D) < batch.copies[band, None]).to(batch.dtype)
    copy_weight = on / on.sum(dim=1, keepdim=True)
    numbers = _activation_table(batch, band)
    groups = batch.activation_groups
    for s, k in enumerate(stepping):
        noise = normal.index_select(0, visit[s, :k].flatten()).view(k, B, all_copies, n_in)
        data = rows.index_select(0, at[s, :k].flatten()).view(k, B, 1, n_in)
        xe = torch.addcmul(data, noise[:, :, :D], scale[:k])
        grad = _band_gradient(
            groups,
            theta[:k],
            {name: value[:k] for name, value in numbers.items()},
            xe,
            copy_weight[:k],
            weight[s, :k],
        )
        theta[:k] -= rate[:k] * grad
    return theta


def fine_tune(
    batch: FSNBatch,
    x: Tensor,
    draws: FineTuneDraws,
    train: Tensor | None = None,
    dataset: Tensor | None = None,
) -> FSNBatch:
    """SRD fine-tuning of every patron at once (spec §5.5).

    Each patron has its own epochs, shuffles, batch size (last partial batch kept) and learning
    rate. At each of its steps a patron takes the mean CEL([T, F], argmax [T, F]) over its
    batch and plain SGD moves its own parameters, θ_p ← θ_p − lr_p·∇θ_p. Patrons outside
    ``train`` (bool (P,)) keep their parameters; PFC parameters move only where
    pfc.trainable. Patrons of nearby batch sizes step together: one step of a band is one
    pass of small per-patron matrix products over their (row, copy) columns, with the
    gradient of ``self_reward``'s loss written out (autograd's bookkeeping would cost more
    than the arithmetic on these small tensors).

    ``x`` is the item dataset, (R, 8) shared or (P, R, 8), or several datasets (N, R, 8) with
    ``dataset`` (P,) the one of each patron. Returns the updated batch.
    """
    P, R = batch.n_patrons, x.shape[-2]
    if x.dim() == 2:
        x, dataset = x[None], torch.zeros(P, dtype=torch.long)
    elif dataset is None:
        dataset = torch.arange(P)
    epochs = batch.epochs if train is None else torch.where(train, batch.epochs, 0)
    if P == 0 or int(epochs.max()) == 0:
        return batch
    size = batch.batch_size.clamp(max=R)
    steps = epochs * torch.div(R + size - 1, size, rounding_mode="floor")
    theta = _flat_parameters(batch)
    pfc_columns = torch.cat(
        [
            torch.full((t[0].numel(),), name in _PFC_PARAMETERS)
            for name, t in batch.parameters().items()
        ]
    )
    frozen = pfc_columns[None, :] & ~batch.pfc_trainable[:, None]
    rate = torch.where(frozen, 0.0, batch.learning_rate[:, None])
    for band in _bands(size, steps, batch.copies):
        theta[band] = _tune_band(
            batch, band, steps[band], theta[band], rate[band], x, dataset, draws
        )
    return batch.with_parameters(_unflatten(batch, theta))


def fine_tune_round(
    batch: FSNBatch,
    x: Tensor,
    fine_tune_seeds: np.ndarray,
    augmentation_seeds: np.ndarray,
    positions: np.ndarray,
    dataset: Tensor | None = None,
) -> FSNBatch:
    """One fine-tuning round of an auction, the same in the market and in a remote agent:
    patron p, at position ``positions[p]`` of its auction, shuffles its rows with the seed
    ``derive_seeds(fine_tune_seeds[p], position)`` and jitters its copies with
    ``derive_seeds(augmentation_seeds[p], position)``, then ``fine_tune`` runs (``x`` and
    ``dataset`` as there)."""
    draws = draw_fine_tune_seeded(
        batch,
        x.shape[-2],
        derive_seeds(fine_tune_seeds, positions),
        derive_seeds(augmentation_seeds, positions),
    )
    return fine_tune(batch, x, draws, dataset=dataset)


# --- Patron factories -------------------------------------------------------------------------


@functools.cache
def _design(kind: str) -> Manifest:
    """The designed FSN (``honest``: spec §4.1 with zero hold and quit biases; ``saboteur``:
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
    base_price: float = 5.0,
    min_buy_price: float = 4.8,
) -> Manifest:
    """An honest FSN (spec §4.1, §4.3): willingness to pay b ~ U(min_buy_price, base_price) sets
    the PG price weight 1/b; hold_bias ~ U(−0.5, 0.5), quit_bias ~ U(0, 0.5); fine-tuning
    epochs ~ {0,1,2}, batch ~ {4..15}, lr ~ U(1e−7, 1e−4). The fine-tuning numbers are always
    drawn (so the same stream gives the same patron either way); ``fine_tune=False`` keeps
    the default settings (no epochs)."""
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


def saboteur_manifest(rng: np.random.Generator, participant: str) -> Manifest:
    """A well-formed FSN that always holds, to drag the price down (paper, Fig. D).

    Sensor and judge are the honest design (b ~ U(4.8, 5.0)); the buy neuron is inert (all
    weights 0, bias −1, so B = −1) and the hold bias is +5. Every ES activation lies in (−1, 1),
    hence L = 0.8·PG − SZ + 5 > 3.2 while Q = 2·PG − 0.5 < 1.5 and B = −1: hold on every input,
    noise or not. It never fine-tunes.
    """
    b = float(rng.uniform(4.8, 5.0))
    return _personalised(
        _design("saboteur"),
        participant,
        "Saboteur: always holds to push the price down.",
        b,
        {},
        FineTuning(),
    )


__all__ = [
    "ACTIONS",
    "ACTIVATION_KINDS",
    "NEURONS",
    "FSNBatch",
    "FineTuneDraws",
    "activations",
    "decide",
    "decision_logits",
    "derive_seeds",
    "draw_fine_tune",
    "draw_fine_tune_blocks",
    "draw_fine_tune_seeded",
    "fine_tune",
    "fine_tune_round",
    "from_manifests",
    "honest_manifest",
    "make_noise",
    "noise_scale",
    "saboteur_manifest",
    "self_reward",
    "standard_normal",
    "to_manifest",
]
