"""What a half-cheetah run answers: its trials grouped by condition, how a condition is named,
and the shape of the result. Its knobs (``CheetahConfig``) and the grid of conditions they span
(``grid_conditions``) are in ``sim.configs``, which the server reads without MuJoCo."""

from __future__ import annotations

from typing import Any

from sim.configs import CheetahConfig, Condition
from sim.experiment import Stopwatch, config_dict

Cells = list[tuple[Condition, int]]
"""Every trial of a grid: its condition and its trial index (0-based), in batch order."""

GRID_ONLY = ("inhibitor", "srd", "lr", "trials", "nominal", "video", "seed")
"""Options no design stage takes (it runs its own conditions, noise-free, without a GIF)."""


def condition_groups(cells: Cells) -> dict[Condition, list[int]]:
    """Batch indices of each condition's trials, conditions in batch order."""
    groups: dict[Condition, list[int]] = {}
    for i, (cond, _) in enumerate(cells):
        groups.setdefault(cond, []).append(i)
    return groups


def condition_label(cond: Condition) -> str:
    """``SRD on (lr 0.0001), inhibitor 2``: how figures and weights.json name a condition."""
    srd = f"SRD on (lr {cond.lr:g})" if cond.srd else "SRD off"
    return f"{srd}, inhibitor {cond.inhibitor:g}"


def run_result(
    config: CheetahConfig, fields: dict[str, Any], artifacts: list[str], watch: Stopwatch
) -> dict[str, Any]:
    """The result of every run (the ``--json`` object): the config, the run's own ``fields``,
    the artifact file names and the elapsed wall time. A design stage's config shows what it
    ran: its backswing gains (null for stages 0–2) and null for the grid-only options."""
    shown = config_dict(config)
    if config.stage is not None:
        shown |= dict.fromkeys(GRID_ONLY)
        shown["backswing"] = config.stage_backswings() or None
    return {
        "config": shown,
        **fields,
        "artifacts": artifacts,
        "elapsed_s": watch.elapsed(),
    }
