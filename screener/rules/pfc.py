"""Rules of the PFC: the judgements read what they are named after (holding at a high price,
PGL, and buying cheap, BC, are right; quitting a good fish, FQ, is wrong), and the verdicts T/F
reward the sensible decisions without a prior."""

from __future__ import annotations

import numpy as np

from agents.manifest import JUDGEMENTS, PFC_SOURCES, VERDICTS
from screener import limits
from screener.findings import ROLE, Checks, check
from screener.rules.connections import Meaning, connection_checks, layer_of
from screener.rules.numbers import Numbers

JUDGEMENT_MEANING: Meaning = {
    ("PGL", "PG"): (+1, True, "counts holding as less right, the higher the price"),
    ("PGL", "L"): (+1, True, "does not count holding at a high price as right"),
    ("BC", "PG"): (-1, True, "counts buying as more right, the higher the price"),
    ("BC", "B"): (+1, True, "does not count buying cheap as right"),
    ("FQ", "SZ"): (+1, True, "does not count quitting a big fish as a false quit"),
    ("FQ", "LSR"): (+1, True, "does not count quitting in a rush as a false quit"),
    ("FQ", "ST"): (+1, True, "does not count quitting its preferred sub-type as a false quit"),
    ("FQ", "Q"): (+1, True, "does not count quitting as a false quit"),
}
"""PFC judgement (target, source) → (sign, relied upon, consequence); every other source may
carry at most PFC_OFF_DESIGN_LIMIT."""
VERDICT_MEANING: Meaning = {
    ("T", "PGL"): (+1, True, "judges holding at a high price to be wrong"),
    ("T", "BC"): (+1, True, "judges buying cheap to be wrong"),
    ("T", "FQ"): (-1, False, "judges a false quit to be right"),
    ("F", "PGL"): (-1, False, "judges holding at a high price to be wrong"),
    ("F", "BC"): (-1, False, "judges buying cheap to be wrong"),
    ("F", "FQ"): (+1, True, "does not judge a false quit to be wrong"),
}
"""PFC verdict (target, source) → (sign, relied upon, consequence)."""
JUDGEMENT_LAYER = layer_of(JUDGEMENTS, PFC_SOURCES, JUDGEMENT_MEANING)
VERDICT_LAYER = layer_of(VERDICTS, JUDGEMENTS, VERDICT_MEANING)


def pfc_checks(n: Numbers) -> list[Checks]:
    """PFC: the judgements read what they are named after; T rewards the sensible decisions."""
    judgement_bias = n.judgement_bias

    def bias_message(j: int, p: int) -> str:
        target = JUDGEMENTS[j]
        return (
            f"{ROLE[target]} {target} has bias {judgement_bias[p, j]:+.3g} (at most "
            f"{limits.JUDGEMENT_BIAS_LIMIT:g} in size): it is decided before it reads anything"
        )

    gap = n.verdict_bias[:, 0] - n.verdict_bias[:, 1]
    return [
        *connection_checks(
            "judgement-sign", n.judgement_weight, JUDGEMENT_LAYER, "judgement-off-design"
        ),
        Checks(
            ("judgement-bias",) * len(JUDGEMENTS),
            JUDGEMENTS,
            np.abs(judgement_bias) > limits.JUDGEMENT_BIAS_LIMIT,
            bias_message,
        ),
        *connection_checks("verdict-sign", n.verdict_weight, VERDICT_LAYER),
        check(
            "verdict-bias",
            "T",
            np.abs(gap) > limits.VERDICT_BIAS_GAP_LIMIT,
            lambda p: (
                f"the verdicts' biases differ by {gap[p]:+.3g} (T − F; at most "
                f"{limits.VERDICT_BIAS_GAP_LIMIT:g} in size): the PFC calls every decision "
                f"{'right' if gap[p] > 0 else 'wrong'} before judging it, and fine-tuning follows"
            ),
        ),
    ]
