"""Robot2NN's planning rules: how plans are imagined, chosen and scored, in the paper's text
(``paper``) and in the reference code (``reference``). No tensors here: a job's options name a
preset, and the server checks them without loading torch."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

MOVE_LIMIT = 36
"""Iterations (moves) of one imagined plan."""
GUARD_FRACTION = 1 / MOVE_LIMIT
"""The guarded loss floors |v_plan| at this fraction of max|v_Σ| before normalising: the mean
that one tile of the largest magnitude adds to the longest plan. A plan worth less than that
is "neither good nor bad" to the robot, so N[v] shrinks linearly towards 0 instead of jumping
to ±1 with gain 1/|v| (docs/lavaland.md)."""


@dataclass(frozen=True)
class PlanningRules:
    """How plans are imagined, chosen and scored: the paper's text or the reference code."""

    n_plans: int
    """Imagined plans per map."""
    executed: Literal["best", "last"]
    """Executed plan: the highest v_plan (paper) or always the last one (reference)."""
    loss_reduction: Literal["sum", "mean"]
    """Loss over plans: summed (paper) or averaged (reference)."""
    anchors: Literal["set", "add"]
    """Target/start tiles set to ±v0 (paper) or ±v0 added through the soft ABA (reference)."""
    final_check: bool
    """Detect a target entered on the last move (paper: within 36 moves; reference: 35)."""
    loss_guard: bool = False
    """Floor |v_plan| at ``GUARD_FRACTION``·max|v_Σ| in N[v] (off in both presets)."""

    @property
    def detection_horizon(self) -> int:
        """Moves within which an entered target counts as reached."""
        return MOVE_LIMIT if self.final_check else MOVE_LIMIT - 1


PRESETS: dict[str, PlanningRules] = {
    "paper": PlanningRules(
        n_plans=4, executed="best", loss_reduction="sum", anchors="set", final_check=True
    ),
    "reference": PlanningRules(
        n_plans=2, executed="last", loss_reduction="mean", anchors="add", final_check=False
    ),
}
"""``paper`` (default: the paper's text) and ``reference`` (the authors' code; reproduces Table 1);
the differences are listed in docs/lavaland.md."""
