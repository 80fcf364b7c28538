"""P Fish Sale Negotiators stacked in one ``FSNBatch`` (parameters on a leading patron axis),
and the exact round trip between manifests and batches (``from_manifests``, ``to_manifest``).
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
import numpy.typing as npt
import torch
from torch import Tensor

from agents.manifest import (
    DECISIONS,
    ES_NEURONS,
    INPUTS,
    JUDGEMENTS,
    PFC_SOURCES,
    VERDICTS,
    BelowThresholdActivation,
    Manifest,
    SelectiveActivation,
    ThresholdActivation,
)

ACTIVATION_KINDS = ("threshold", "below_threshold", "selective")
"""Activation kinds by code, as stored in ``FSNBatch.es_kind``."""
THRESHOLD, BELOW_THRESHOLD, SELECTIVE = range(3)

PARAMETERS = (
    "es_weight",
    "es_bias",
    "fc_weight",
    "fc_bias",
    "judgement_weight",
    "judgement_bias",
    "verdict_weight",
    "verdict_bias",
)
PFC_PARAMETERS = frozenset(("judgement_weight", "judgement_bias", "verdict_weight", "verdict_bias"))


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
    ``participants`` and ``descriptions`` (1-D arrays of str objects: a sub-batch picks its
    names as it picks its tensors, without a Python loop over the patrons).
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
    participants: npt.NDArray[np.object_]
    descriptions: npt.NDArray[np.object_]

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
        return {name: getattr(self, name) for name in PARAMETERS}

    def with_parameters(self, params: dict[str, Tensor]) -> FSNBatch:
        """A copy of the batch with some trainable tensors replaced."""
        changes: dict[str, Any] = dict(params)
        return dataclasses.replace(self, **changes)

    def to(self, dtype: torch.dtype) -> FSNBatch:
        """The batch with its real-valued tensors in ``dtype`` (itself when they already are)."""
        if self.dtype == dtype:
            return self
        changes: dict[str, Any] = {
            f.name: value.to(dtype)
            for f in dataclasses.fields(self)
            if isinstance(value := getattr(self, f.name), Tensor) and value.is_floating_point()
        }
        return dataclasses.replace(self, **changes)

    def select(self, index: Sequence[int] | Tensor | np.ndarray | slice) -> FSNBatch:
        """The sub-batch of the patrons at ``index`` (in that order; a slice gives views)."""
        if isinstance(index, slice):
            sliced = {f.name: getattr(self, f.name)[index] for f in dataclasses.fields(self)}
            return FSNBatch(**sliced)
        idx = torch.as_tensor(index, dtype=torch.long)
        positions = idx.numpy()
        fields: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Tensor):
                fields[f.name] = value.index_select(0, idx)
            else:
                fields[f.name] = value[positions]
        return FSNBatch(**fields)


def concat(batches: Sequence[FSNBatch]) -> FSNBatch:
    """The patrons of ``batches`` one after another in one batch: the same batch as
    ``from_manifests`` of their manifests in that order (each row is its manifest's alone)."""
    if not batches:
        raise ValueError("at least one batch is needed")
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(FSNBatch):
        values = [getattr(batch, f.name) for batch in batches]
        if isinstance(values[0], Tensor):
            fields[f.name] = torch.cat(values)
        else:
            fields[f.name] = np.concatenate(values)
    return FSNBatch(**fields)


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
        participants=np.array([m.participant for m in manifests], dtype=object),
        descriptions=np.array([m.description for m in manifests], dtype=object),
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
