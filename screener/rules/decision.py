"""Rules of the decision layer (FC): B is driven down by PG and up by SZ, LSR, ST; L (hold,
want a lower price) and Q (quit) are driven by PG; buying is the default intent."""

from __future__ import annotations

from agents.manifest import DECISIONS, ES_NEURONS
from screener.findings import Checks, check
from screener.rules.connections import Meaning, connection_checks, layer_of
from screener.rules.numbers import Numbers

DECISION_MEANING: Meaning = {
    ("B", "PG"): (-1, True, "buys more as the price rises"),
    ("B", "SZ"): (+1, True, "buys less, the bigger the fish"),
    ("B", "LSR"): (+1, True, "buys less when the others rush to buy"),
    ("B", "ST"): (+1, True, "buys less when the fish is of its preferred sub-type"),
    ("L", "PG"): (+1, True, "holds less as the price rises"),
    ("L", "SZ"): (-1, False, "holds out for a lower price more, the bigger the fish"),
    ("L", "LSR"): (-1, False, "holds back more when the others rush to buy"),
    ("L", "ST"): (-1, False, "holds back more when the fish is of its preferred sub-type"),
    ("Q", "PG"): (+1, True, "quits less as the price rises"),
    ("Q", "SZ"): (-1, False, "quits more, the bigger the fish"),
    ("Q", "LSR"): (-1, False, "quits more when the others rush to buy"),
    ("Q", "ST"): (-1, False, "quits more when the fish is of its preferred sub-type"),
}
"""FC (target, source) → (sign, relied upon, what a wrong sign makes the model do)."""
DECISION_LAYER = layer_of(DECISIONS, ES_NEURONS, DECISION_MEANING)


def decision_checks(n: Numbers) -> list[Checks]:
    """FC: the sign of every connection, and buying as the default intent."""
    bias = n.fc_bias
    return [
        *connection_checks("decision-sign", n.fc_weight, DECISION_LAYER),
        check(
            "buy-intent",
            "B",
            ~(bias[:, 0] > bias[:, 1:].max(axis=1)),
            lambda p: (
                f"the buy neuron B has bias {bias[p, 0]:+.3g}, not above the hold neuron L "
                f"({bias[p, 1]:+.3g}) and the quit neuron Q ({bias[p, 2]:+.3g}): with every "
                "sensor quiet (an ordinary fish at its own price) the model does not buy"
            ),
        ),
    ]
