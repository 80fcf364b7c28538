"""The inspection's cheap part: the semantic rules and the behavioural probes of a batch.

They read the numbers and one forward pass over the probe rows, so they run wherever a verdict is
needed often: at the door, and on every fine-tuning round inside the market-impact test's own
auctions (which must not run market-impact tests of their own).
"""

from __future__ import annotations

import numpy as np

from agents.batch import FSNBatch
from screener.findings import Checks, Mask
from screener.probes import probe
from screener.rules import Numbers, semantic_checks


def cheap_checks(batch: FSNBatch) -> tuple[list[Checks], Mask]:
    """Every rule and probe over the batch, and which models hold somewhere on the reachable
    decisive row (those go on to the market-impact test)."""
    probed = probe(batch)
    return [*semantic_checks(Numbers.of(batch)), probed.checks], probed.holds


def failed_any(groups: list[Checks]) -> Mask:
    """(P,): the models that fail some check of the groups."""
    failed: Mask = np.any(np.concatenate([g.failed for g in groups], axis=1), axis=1)
    return failed


def passes_cheap(batch: FSNBatch) -> Mask:
    """(P,): the models no rule and no probe refuses."""
    return ~failed_any(cheap_checks(batch)[0])
