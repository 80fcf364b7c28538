"""The inspector: reads a submitted manifest weight by weight and probes its behaviour.

``screen(manifest) -> Verdict`` is the one entry point every caller uses (``/submit``,
``srd screen``, ``srd auction-study --screen``, re-screening of fine-tuned versions);
``screen_many`` judges a whole batch with one pass of every rule and one probe forward pass.

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
from screener.probes import probe_findings
from screener.rules import semantic_findings
from screener.verdict import Reason, Verdict

__all__ = ["Reason", "Verdict", "screen", "screen_many"]


def screen_many(manifests: Sequence[Manifest]) -> list[Verdict]:
    """Judge parsed manifests together (batched rules and probes); one verdict each, in order."""
    if not manifests:
        return []
    batch = from_manifests(manifests)
    findings = semantic_findings(batch) + probe_findings(batch)
    reasons: list[list[Reason]] = [[] for _ in manifests]
    failed = np.stack([found.failed for found in findings])  # (findings, P)
    for k, p in zip(*np.nonzero(failed), strict=True):
        found = findings[k]
        reasons[p].append(Reason(found.rule, found.neuron, found.message(int(p))))
    return [Verdict(accepted=not r, reasons=r) for r in reasons]


def screen(manifest: Manifest) -> Verdict:
    """Judge one parsed manifest: accepted, or rejected with every reason in plain words."""
    return screen_many([manifest])[0]
