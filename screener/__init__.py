"""The inspector: reads a submitted manifest weight by weight and probes its behaviour.

``screen(manifest) -> Verdict`` is the one entry point every caller uses (``/submit``,
``srd screen``, ``srd auction-study --screen``, re-screening of fine-tuned versions);
``screen_many`` judges a whole batch at once: every rule runs once over the batch's arrays and
the probes share forward passes, with the same verdict for each manifest as ``screen``.

A manifest is accepted when no rule and no probe finds anything: the semantic rules
(``screener.rules``) read each named weight against the meaning the paper gives its neuron,
the behavioural probes (``screener.probes``) watch its decisions on a grid of items. Every
threshold is in ``screener.limits`` with its rationale.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from agents.manifest import Manifest
from agents.negotiator import from_manifests
from screener.findings import Checks
from screener.probes import probe_checks
from screener.rules import Numbers, semantic_checks
from screener.verdict import Reason, Verdict

__all__ = ["Reason", "Verdict", "screen", "screen_many"]


def screen_many(manifests: Sequence[Manifest]) -> list[Verdict]:
    """Judge parsed manifests together (batched rules and probes); one verdict each, in order."""
    if not manifests:
        return []
    batch = from_manifests(manifests)
    groups = [*semantic_checks(Numbers.of(batch)), probe_checks(batch)]
    failed = np.concatenate([g.failed for g in groups], axis=1)  # (P, checks)
    reasons: list[list[Reason]] = [[] for _ in manifests]
    if failed.any():
        checks: list[tuple[Checks, int]] = [(g, k) for g in groups for k in range(len(g.rules))]
        for p, column in zip(*np.nonzero(failed), strict=True):
            group, k = checks[column]
            reasons[p].append(Reason(group.rules[k], group.neurons[k], group.message(k, int(p))))
    return [Verdict(accepted=not r, reasons=r) for r in reasons]


def screen(manifest: Manifest) -> Verdict:
    """Judge one parsed manifest: accepted, or rejected with every reason in plain words."""
    return screen_many([manifest])[0]
