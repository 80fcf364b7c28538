"""What every semantic rule reads: a batch's numbers (``Numbers``), the indices of the ES
neurons and of the inputs, the inputs each ES neuron is named after, the base item and the
sub-types, and where a threshold neuron crosses its centre (``reference_point``)."""

from __future__ import annotations

import dataclasses
import functools
import itertools

import numpy as np

from agents.batch import FSNBatch
from agents.manifest import ES_NEURONS
from screener import limits
from screener.findings import Array, Mask

PG, SZ, LSR, ST = range(4)
PRICE, LENGTH, WEIGHT, GILL, ST1, ST2, ST3, DEMAND = range(8)
QUALITY_INPUTS = (LENGTH, WEIGHT, GILL)
SUBTYPE_INPUTS = (ST1, ST2, ST3)

SENSOR_INPUTS = {
    "PG": (PRICE,),
    "SZ": (LENGTH, WEIGHT),
    "LSR": (DEMAND,),
    "ST": SUBTYPE_INPUTS,
}
"""The inputs each ES neuron is named after."""
BASE = np.array(limits.BASE_ROW)
SUBTYPES = np.array(list(itertools.product((0.5, -0.5), repeat=3)))
"""The 8 sub-types; row 0 is the preferred (½, ½, ½)."""
NAMED_COLUMNS = tuple(np.array(SENSOR_INPUTS[name], dtype=np.intp) for name in ES_NEURONS)
"""Per ES neuron: the inputs it is named after."""
OTHER_COLUMNS = tuple(np.setdiff1d(np.arange(len(BASE)), named) for named in NAMED_COLUMNS)
"""Per ES neuron: the inputs it is not named after."""


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
    batch_size: Array

    @classmethod
    def of(cls, batch: FSNBatch) -> Numbers:
        """Read the arrays out of a batch."""
        return cls(**{name: getattr(batch, name).double().numpy() for name in _NUMBER_FIELDS})

    @functools.cached_property
    def willingness_to_pay(self) -> Array:
        """The price where PG crosses its threshold on the base fish (NaN if PG does not rise
        with the price)."""
        return reference_point(self, PG)


_NUMBER_FIELDS = tuple(f.name for f in dataclasses.fields(Numbers))


def reference_point(n: Numbers, neuron: int) -> Array:
    """Where a threshold neuron crosses its centre c on the base item, as a value of the inputs
    it is named after (moved together): (c − bias − other inputs) / Σ named weights; NaN unless
    the named weights sum to more than 0."""
    named, other = NAMED_COLUMNS[neuron], OTHER_COLUMNS[neuron]
    weights = n.es_weight[:, neuron]
    slope = weights[:, named].sum(axis=1)
    # Sums along each row, not matrix products: a product's kernel depends on the batch size,
    # and with absurd weights (1e308) its rounding decides inf or NaN, so a model's reasons
    # would depend on the batch it is judged in. The other inputs alone, not every input less
    # the named ones: a named weight of 1.8e308 made both sums inf and the point NaN.
    rest = (weights[:, other] * BASE[other]).sum(axis=1) + n.es_bias[:, neuron]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(slope > 0, (n.es_c[:, neuron] - rest) / slope, np.nan)


def outside(values: Array, low: float | Array, high: float | Array) -> Mask:
    """Outside [low, high] (NaN counts as inside: another rule reports it)."""
    return (values < low) | (values > high)
