"""Semantic rules: each named weight read against the meaning the paper gives its neuron.

Paper, "The Server and Fish Sale Negotiator": PG lights up when the price is above the
participant's willingness to pay (and a little when the fish is poor), SZ grows with length and
weight, LSR with the previous buy fraction (others are rushing), ST peaks at the preferred
sub-type; B is driven down by PG and up by SZ, LSR, ST; L (hold, want a lower price) and Q (quit)
are driven by PG. The PFC judges: holding at a high price (PGL) and buying cheap (BC) are right
(T), quitting a good fish (FQ) is wrong (F). Every rule below is vectorised over a batch of P
manifests; the thresholds live in ``screener.limits``.

Modules, one job each (a module per layer of rules):

* ``numbers``: what every rule reads (``Numbers``, the neuron and input indices, the base item);
* ``connections``: a layer's meaning as signs and the rule checking its weights against it;
* ``sensors``: the external sensors PG, SZ, LSR, ST;
* ``decision``: the decision layer B, L, Q;
* ``pfc``: the PFC's judgements and verdicts;
* ``settings``: augmentation and fine-tuning settings;
* ``magnitude``: no gigantic numbers, in any layer.
"""

from __future__ import annotations

from screener.findings import Checks
from screener.rules.decision import decision_checks
from screener.rules.magnitude import magnitude_checks
from screener.rules.numbers import SUBTYPES, Numbers
from screener.rules.pfc import pfc_checks
from screener.rules.sensors import (
    activation_checks,
    off_design_checks,
    price_checks,
    size_demand_checks,
    subtype_checks,
)
from screener.rules.settings import setting_checks

__all__ = ["SUBTYPES", "Numbers", "semantic_checks"]


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
