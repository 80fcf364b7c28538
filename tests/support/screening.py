"""What the screener tests read from verdicts, and the names a verdict may use."""

from __future__ import annotations

from screener import Verdict

KNOWN_NEURONS = {"PG", "SZ", "LSR", "ST", "B", "L", "Q", "PGL", "BC", "FQ", "T", "F"}
"""Every neuron of the Fish Sale Negotiator: a reason names one of these (or a manifest block)."""

PROBE_RULES = {
    "probe-non-finite",
    "buys-cheap",
    "always-holds",
    "always-quits",
    "never-buys",
    "holds-on-most-items",
    "refuses-far-too-expensive",
    "quits-far-too-expensive",
    "buy-falls-with-price",
    "sincere-hold",
    "knife-edge",
}
"""The rule names of the behavioural probes (the semantic rules use other names)."""


def rules_of(verdict: Verdict) -> set[tuple[str, str]]:
    """The (rule, neuron) pairs of a verdict."""
    return {(r.rule, r.neuron) for r in verdict.reasons}


def message_of(verdict: Verdict, rule: str, neuron: str) -> str:
    """The message of the one reason with that rule and neuron."""
    (message,) = [r.message for r in verdict.reasons if (r.rule, r.neuron) == (rule, neuron)]
    return message
