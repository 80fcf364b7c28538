"""What a half-cheetah run is asked and what it answers: the knobs (``CheetahConfig``), the
grid of conditions they span, and the shape of the result."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pydantic import Field

from sim.experiment import Cost, Stopwatch, config_dict

TRIAL_STEP_COST_S = 3e-5
"""Compute of one trial advancing one 0.01 s step (MuJoCo plus the network), for the job
budget: about three times the grid engine's measured cost per step and core."""
Gains = Annotated[
    tuple[Annotated[float, Field(ge=-100, le=100)], ...], Field(min_length=1, max_length=32)
]


@dataclass(frozen=True)
class CheetahConfig:
    """HalfCheetahSRD: the grid backswing × inhibitor × SRD (× learning rate) × trial."""

    backswing: Gains = (1.0, 2.0, 3.0, 4.0, 5.0)
    """BS neuron gains to run (how hard the back thigh answers the pitch signal)."""
    inhibitor: Annotated[
        tuple[Annotated[float, Field(ge=0, le=100)], ...], Field(min_length=1, max_length=32)
    ] = (0.0, 2.0)
    """Inhibitor values of the stop command (0: never stop; 2: stop in the scheduled windows)."""
    srd: Literal["on", "off", "both"] = "both"
    """Self-reward optimisation during the trial: on, off or both (paired, same weights)."""
    trials: Annotated[int, Field(ge=1, le=1000)] = 7
    """Seeded trials per condition (weight noise differs per trial; --nominal runs one)."""
    steps: Annotated[int, Field(ge=1, le=1_000_000)] | None = None
    """Simulation steps of 0.01 s (default 3600; stages: 400 for 0, 1200 for 1–4)."""
    nominal: bool = False
    """Noise-free designed weights (deterministic, one trial per condition)."""
    stage: Annotated[int, Field(ge=0, le=4)] | None = None
    """Run one of the appendix's design stages 0–4 instead of the main grid."""
    lr: Annotated[
        tuple[Annotated[float, Field(gt=0, le=100)], ...], Field(min_length=1, max_length=32)
    ] = (1e-4,)
    """SGD learning rate(s) of SRD; several values sweep them (an extra grid axis)."""
    threads: Annotated[int, Field(ge=1, le=64)] = 2
    """Threads stepping MuJoCo in parallel."""
    video: bool = True
    """Render a GIF of one trial when an offscreen OpenGL context is available."""
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    """Seeds the per-trial weight noise: same seed, same numbers."""

    def cost(self) -> Cost:
        """Estimated compute: every trial of every condition, step by step."""
        from sim.cheetah.world import TRIAL_STEPS  # here: the config itself needs no MuJoCo

        trials = len(grid_conditions(self)) * (1 if self.nominal else self.trials)
        steps = TRIAL_STEPS if self.steps is None else self.steps
        return Cost(trials * steps * TRIAL_STEP_COST_S, "trials")


@dataclass(frozen=True)
class Condition:
    """One cell of the grid."""

    backswing: float
    inhibitor: float
    srd: bool
    lr: float | None


Cells = list[tuple[Condition, int]]
"""Every trial of a grid: its condition and its trial index (0-based), in batch order."""


def grid_conditions(config: CheetahConfig) -> list[Condition]:
    """Conditions in report order: SRD on (each lr) before off, then backswing, inhibitor."""
    variants: list[tuple[bool, float | None]] = []
    if config.srd in ("on", "both"):
        variants += [(True, lr) for lr in config.lr]
    if config.srd in ("off", "both"):
        variants.append((False, None))
    return [
        Condition(float(b), float(i), on, lr)
        for (on, lr), b, i in itertools.product(variants, config.backswing, config.inhibitor)
    ]


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
    the artifact file names and the elapsed wall time."""
    return {
        "config": config_dict(config),
        **fields,
        "artifacts": artifacts,
        "elapsed_s": watch.elapsed(),
    }
