"""The inspection's cheap part: the semantic rules, the behavioural probes and the noisy scan of
the decisive row over a batch.

They read the numbers and a few forward passes, so they run wherever a verdict is needed often:
at the door, and on every fine-tuning round inside the market-impact test's own auctions (which
must not run market-impact tests of their own).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from agents.batch import FSNBatch
from screener.findings import Checks, Mask
from screener.noisy import Noisy, evaluate
from screener.probes import Probed, probe
from screener.rules import Numbers, semantic_checks


class Cheap(NamedTuple):
    """A batch with every rule, probe and noisy check of it; which models hold somewhere on the
    reachable decisive row, clean or as the market sees them (those go on to the market-impact
    test); and the probes and the noisy scan themselves (their numbers are evidence)."""

    batch: FSNBatch
    groups: list[Checks]
    holds: Mask
    probed: Probed
    noisy: Noisy


def cheap_checks(batch: FSNBatch) -> Cheap:
    """Every rule, probe and noisy check over the batch (see ``Cheap``)."""
    probed = probe(batch)
    noisy = evaluate(batch)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # absurd weights
        # overflow the rules' arithmetic: the magnitude rule refuses them, and the other
        # reasons say "not finite" in words (``findings.fmt``), not a warning on stderr
        rules = semantic_checks(Numbers.of(batch))
    groups = [*rules, probed.checks, noisy.checks]
    return Cheap(batch, groups, probed.holds | noisy.holds, probed, noisy)


def failed_any(groups: list[Checks]) -> Mask:
    """(P,): the models that fail some check of the groups."""
    failed: Mask = np.any(np.concatenate([g.failed for g in groups], axis=1), axis=1)
    return failed


def passes_cheap(batch: FSNBatch) -> Mask:
    """(P,): the models no rule, probe or noisy check refuses."""
    return ~failed_any(cheap_checks(batch).groups)
