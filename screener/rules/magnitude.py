"""The magnitude rule, over every layer: no gigantic number hides a neuron's real effect."""

from __future__ import annotations

import numpy as np

from agents.batch import SELECTIVE
from agents.manifest import DECISIONS, ES_NEURONS, INPUTS, JUDGEMENTS, PFC_SOURCES, VERDICTS
from screener import limits
from screener.findings import ROLE, Checks
from screener.rules.numbers import Numbers

MAGNITUDE_LAYERS = (
    (ES_NEURONS, (*INPUTS, "bias", "threshold centre c")),
    (DECISIONS, (*ES_NEURONS, "bias")),
    (JUDGEMENTS, (*PFC_SOURCES, "bias")),
    (VERDICTS, (*JUDGEMENTS, "bias")),
)
"""Per layer, its neurons and the numbers of each that the magnitude rule reads."""
MAGNITUDE_NEURONS = tuple(name for names, _ in MAGNITUDE_LAYERS for name in names)
MAGNITUDE_COLUMNS = tuple(columns for names, columns in MAGNITUDE_LAYERS for _ in names)


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
