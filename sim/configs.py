"""The options of the worlds' experiments (robot fish, lavaland, half-cheetah): their fields,
bounds and cost estimates, in one module that loads no simulation (no torch, numba, MuJoCo or
Gymnasium). The server checks a job's options with them and describes them in its OpenAPI
document without loading any of those; the worlds' modules use them as they are."""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Literal

from pydantic import Field

from agents.planning import PRESETS
from sim.experiment import Cost, distinct

# --- robot fish 1D --------------------------------------------------------------------------

FISH_STEP_COST_S = 4e-4
"""Compute of one step with SRD training, for the job budget: twice the measured 0.2 ms (the
12000-step run takes about 2.5 s); without SRD half of it."""


@dataclass(frozen=True)
class FishConfig:
    """Robot fish 1D: FishNN on the ring tape, with or without SRD training."""

    SCHEMA_RULES: ClassVar[tuple[dict[str, Any], ...]] = (
        {  # training's options belong to a run that trains
            "if": {"properties": {"srd": {"const": False}}, "required": ["srd"]},
            "then": {"not": {"anyOf": [{"required": [n]} for n in ("lr", "memory")]}},
        },
    )
    """``problems``'s rule across options, as JSON Schema (``sim.experiment.config_schema``)."""

    steps: Annotated[int, Field(ge=1, le=10_000_000)] = 12000
    """Simulation steps (the paper's figure uses 12000; the fish stops earlier only if it dies)."""
    srd: bool = True
    """Self-reward training on (every ``memory`` steps an Adam step on CEL(z, argmax z))."""
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    """Seed for the API; the robot fish has no randomness, so every seed gives the same run."""
    memory: Annotated[int, Field(ge=1, le=10_000)] = 8
    """mem: steps whose PFC verdicts [T, F] are summed into z before each SRD update."""
    lr: Annotated[float, Field(gt=0, le=10)] = 0.002
    """Adam learning rate of the SRD updates (betas (0.5, 0.999), over all parameters)."""
    average_every: Annotated[int, Field(ge=1, le=100_000)] = 24
    """Window (steps) of the averaged-energy panel of the figure."""

    def cost(self) -> Cost:
        """Estimated compute: linear in the steps."""
        return Cost(self.steps * FISH_STEP_COST_S * (1.0 if self.srd else 0.5), "steps")

    def problems(self, given: frozenset[str] = frozenset()) -> list[dict[str, str]]:
        """Training's options ``given`` (named by the user) with no training (``srd`` off)."""
        if self.srd:
            return []
        return [
            {"field": name, "message": f"with srd off nothing is trained: it does not take {name}"}
            for name in ("lr", "memory")
            if name in given
        ]


# --- lavaland --------------------------------------------------------------------------------

MAX_MAPS = 65536
"""Bound on evaluation and training maps per run (memory and time of one job)."""
MAX_REPEATS = 100
"""Bound on repeats per run."""
MAX_PLANS = 16
"""Bound on imagined plans per map."""
PLAN_EVAL_COST_S = 6e-5
"""Compute of evaluating one plan on one map, for the job budget: twice the measured 27 µs
(4096 maps × 4 plans in 0.44 s), the walk and the tile-count rows included."""
LAVALAND_STEP_COST_S = {"fused": 6e-4, "autograd": 1.6e-2}
"""Compute of one SRD step (one training map), for the job budget: twice the slowest measured
0.26 ms (fused) and 7.3 ms (autograd) per step."""
RUN_COST_S = 5.0
"""Compute of a run besides its repeats: maps, figures, the GIF, loading the compiled step."""


@dataclass(frozen=True)
class LavalandConfig:
    """Robot2NN in lavaland: evaluate untrained, SRD-train one epoch, evaluate again."""

    SCHEMA_RULES: ClassVar[tuple[dict[str, Any], ...]] = (
        {  # training's options belong to a run that trains
            "if": {"properties": {"train_maps": {"const": 0}}, "required": ["train_maps"]},
            "then": {
                "not": {"anyOf": [{"required": [n]} for n in ("lr", "loss_guard", "srd_step")]}
            },
        },
    )
    """``problems``'s rule across options, as JSON Schema (``sim.experiment.config_schema``)."""

    project: Literal["A", "compare-A", "lava-A", "lava-noav-A"] = "A"
    """The paper's project: A, compare-A, lava-A or lava-noav-A."""
    preset: Literal["paper", "reference"] = "paper"
    """paper: 4 plans, best plan executed, summed loss, anchors set; reference: the v1 code."""
    eval_maps: Annotated[int, Field(ge=1, le=MAX_MAPS)] = 4096
    """Evaluation maps (accuracy = reached / eval_maps)."""
    train_maps: Annotated[int, Field(ge=0, le=MAX_MAPS)] = 4096
    """Training maps, one SGD step each (0 skips training; accuracy_srd is then null)."""
    repeats: Annotated[int, Field(ge=1, le=MAX_REPEATS)] = 1
    """Independent experiments (the paper's expts 1-4): fresh model, coins and order each."""
    n_plans: Annotated[int, Field(ge=0, le=MAX_PLANS)] = 0
    """Imagined plans per map; 0 = the preset's (paper 4, reference 2)."""
    lr: Annotated[float, Field(gt=0, le=1)] = 1e-4
    """SGD learning rate."""
    loss_guard: bool = False
    """Guarded loss: v/max(|v|, max|v_Σ|/36) in N[v] (off: the paper's v/|v| and its failures)."""
    srd_step: Literal["fused", "autograd"] = "fused"
    """fused: the compiled SRD step; autograd: the same step through torch autograd (slower)."""
    gif_map: Annotated[int, Field(ge=0, le=MAX_MAPS - 1)] = 0
    """Evaluation map animated in trajectory.gif (an index below eval_maps)."""
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    """Seed of every random stream (maps, coins, training order)."""

    def cost(self) -> Cost:
        """Estimated compute: evaluations and SRD steps, linear in each count; repeats drive
        it when there are several, else the larger of the two map counts."""
        n_plans = self.n_plans or PRESETS[self.preset].n_plans
        evaluation = 2 * self.eval_maps * n_plans * PLAN_EVAL_COST_S
        training = self.train_maps * LAVALAND_STEP_COST_S[self.srd_step]
        option = "eval_maps" if evaluation >= training else "train_maps"
        seconds = RUN_COST_S + self.repeats * (evaluation + training)
        return Cost(seconds, "repeats" if self.repeats > 1 else option)

    def problems(self, given: frozenset[str] = frozenset()) -> list[dict[str, str]]:
        """A ``gif_map`` past the evaluation maps; training's options ``given`` (named by the
        user) with no training (``train_maps`` 0)."""
        found = []
        if self.gif_map >= self.eval_maps:
            found.append(
                {
                    "field": "gif_map",
                    "message": f"must be below eval-maps ({self.eval_maps}): the GIF animates "
                    f"one of the evaluation maps, 0 to {self.eval_maps - 1}",
                }
            )
        if self.train_maps == 0:
            found += [
                {
                    "field": name,
                    "message": "with train-maps 0 nothing is trained: it does not take "
                    + name.replace("_", "-"),
                }
                for name in ("lr", "loss_guard", "srd_step")
                if name in given
            ]
        return found


# --- half-cheetah ----------------------------------------------------------------------------

TRIAL_STEPS = 3600
"""Steps of 0.01 s in one trial of the main experiment (36 s)."""
TRIAL_STEP_COST_S = 3e-5
"""Compute of one trial advancing one 0.01 s step (MuJoCo plus the network), for the job
budget: about three times the grid engine's measured cost per step and core."""
PLOT_CELL_COST_S = 0.06
"""Drawing one cell of the grid (its mean line and band in the displacement figure), for the
job budget: about 1.5 times the measured 30–47 ms."""
RUN_SETUP_COST_S = 0.03
"""Setting up one trial (its model, its noise, its row of results): about twice the measured
14 ms, whatever its steps."""
DESIGN_STEPS = 1201
"""12 s runs of the design stages 1–4, counted as the reference counts them: it steps while
MuJoCo's time, 0.01 added per step in floating point, is below 12 s, which takes 1201 steps
(the main grid's 36 s take 3600)."""
DEVTEST_STEPS = 401
"""4 s runs of design stage 0 (401 steps, counted the same way)."""
STAGE0_STRENGTHS = (-2.0, -1.0, -0.5, 0.25, 0.5, 0.75, 1.0, 2.0, 3.0)
"""Actuator strengths s tried by the stage-0 devtest."""
STAGE2_SWING_FROM = 250
"""Stage 2: the front thigh is swung forward from this step on."""
STAGE2_WINDOW = 50
"""Stage 2 averages the neurons over this many steps before and after the swing starts."""
STAGE4_DEFAULT_BACKSWING = 5.0
"""Stage 4 uses this backswing when the grid's default is left unchanged."""
STAGE_COST_S = 2.0
"""Compute of a design stage besides its steps (its figures, poses and set-up), for the job
budget: about 1.5 times the measured 0.7–1.3 s."""
STAGE_ONLY_OF_GRID = ("trials", "nominal")
"""Options of the grid's trials that no design stage takes (a stage runs noise-free; it takes
``--seed``, as every experiment command does, and has no use for it)."""
MAX_CELLS = 512
"""Most cells (backswing × inhibitor × SRD variants) of one grid: its figures draw a panel per
variant and inhibitor, a line per backswing (the default grid has 20)."""
MAX_RUNS = 4096
"""Most trials of one grid (cells × trials): its result lists every run (about 0.2 KB each,
so a job's result stays under a megabyte to send) and its weights artifact every run's
weights (2.4 KB each); the default grid may take 204 trials."""
_UNIQUE = {"uniqueItems": True}
Gains = Annotated[
    tuple[Annotated[float, Field(ge=-100, le=100)], ...],
    Field(min_length=1, max_length=32, json_schema_extra=_UNIQUE),
    distinct("gain", "more trials: raise trials"),
]


GRID_AXES = ("backswing", "inhibitor", "srd", "lr")
"""The fields of ``CheetahConfig`` that span the main grid."""


@dataclass(frozen=True)
class CheetahConfig:
    """HalfCheetahSRD: the grid backswing × inhibitor × SRD (× learning rate) × trial."""

    SCHEMA_RULES: ClassVar[tuple[dict[str, Any], ...]] = (
        {  # a design stage runs its own conditions (stage 4 takes backswing)
            "if": {"required": ["stage"], "properties": {"stage": {"type": "integer"}}},
            "then": {
                "not": {
                    "anyOf": [
                        {"required": [n]}
                        for n in ("inhibitor", "srd", "lr", "trials", "nominal", "video")
                    ]
                }
            },
        },
        {
            "if": {  # a stage but 4 (null is no stage: the grid, which takes backswing)
                "required": ["stage"],
                "properties": {"stage": {"type": "integer", "not": {"const": 4}}},
            },
            "then": {"not": {"required": ["backswing"]}},
        },
        {
            "if": {"required": ["stage"], "properties": {"stage": {"const": 2}}},
            "then": {"properties": {"steps": {"minimum": STAGE2_SWING_FROM + STAGE2_WINDOW}}},
        },
        {  # nominal runs one noise-free trial (trials 1 says so); SRD off trains nothing
            "if": {"required": ["nominal"], "properties": {"nominal": {"const": True}}},
            "then": {"properties": {"trials": {"const": 1}}},
        },
        {
            "if": {"required": ["srd"], "properties": {"srd": {"const": "off"}}},
            "then": {"not": {"required": ["lr"]}},
        },
    )
    """``problems``'s rules across options, as JSON Schema (``sim.experiment.config_schema``)."""

    backswing: Gains = (1.0, 2.0, 3.0, 4.0, 5.0)
    """BS neuron gains to run (how hard the back thigh answers the pitch signal)."""
    inhibitor: Annotated[
        tuple[Annotated[float, Field(ge=0, le=100)], ...],
        Field(min_length=1, max_length=32, json_schema_extra=_UNIQUE),
        distinct("inhibitor value", "more trials: raise trials"),
    ] = (0.0, 2.0)
    """Inhibitor values of the stop command (0: never stop; 2: stop in the scheduled windows)."""
    srd: Literal["on", "off", "both"] = "both"
    """Self-reward optimisation during the trial: on, off or both (paired, same weights)."""
    trials: Annotated[int, Field(ge=1, le=1000)] = 7
    """Seeded trials per condition (weight noise differs per trial; --nominal runs one)."""
    steps: Annotated[int, Field(ge=1, le=1_000_000)] | None = None
    """Simulation steps of 0.01 s (default 3600; stages: 401 for 0, 1201 for 1–4)."""
    nominal: bool = False
    """Noise-free designed weights (deterministic, one trial per condition)."""
    stage: Annotated[int, Field(ge=0, le=4)] | None = None
    """Run one of the appendix's design stages 0–4 instead of the main grid."""
    lr: Annotated[
        tuple[Annotated[float, Field(gt=0, le=100)], ...],
        Field(min_length=1, max_length=32, json_schema_extra=_UNIQUE),
        distinct("learning rate", "more trials: raise trials"),
    ] = (1e-4,)
    """SGD learning rate(s) of SRD; several values sweep them (an extra grid axis)."""
    threads: Annotated[int, Field(ge=1, le=64)] = 2
    """Threads stepping MuJoCo in parallel."""
    video: bool = True
    """Render a GIF of one trial when an offscreen OpenGL context is available."""
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    """Seeds the per-trial weight noise: same seed, same numbers."""

    def stage_backswings(self) -> list[float]:
        """The backswing gains a design stage runs: none for stages 0–2 (no BS neuron), 0 for
        stage 3, the configured ones for stage 4 (5 when none is given: ``settled``)."""
        if self.stage == 3:
            return [0.0]
        if self.stage != 4:
            return []
        return list(self.backswing)

    def settled(self, given: frozenset[str]) -> CheetahConfig:
        """This config with the defaults that depend on what was given: stage 4 without a
        backswing runs 5 alone (the grid's default list, 1 to 5, given as such, runs the
        five)."""
        if self.stage == 4 and "backswing" not in given:
            return dataclasses.replace(self, backswing=(STAGE4_DEFAULT_BACKSWING,))
        return self

    def cost(self) -> Cost:
        """Estimated compute: every trial of every condition, its set-up and its steps, and
        each condition's share of the figures (a design stage: its own trials, and ``steps``
        to lower)."""
        if self.stage is not None:
            runs = len(STAGE0_STRENGTHS) + 1 if self.stage == 0 else 1
            runs = max(runs, len(self.stage_backswings()))
            steps = self.steps or (DEVTEST_STEPS if self.stage == 0 else DESIGN_STEPS)
            return Cost(STAGE_COST_S + runs * steps * TRIAL_STEP_COST_S, "steps")
        cells = len(grid_conditions(self))
        trials = cells * (1 if self.nominal else self.trials)
        steps = TRIAL_STEPS if self.steps is None else self.steps
        seconds = trials * (RUN_SETUP_COST_S + steps * TRIAL_STEP_COST_S)
        # the option to lower: trials, unless there is one trial a cell and steps are given
        many = not self.nominal and self.trials > 1
        option = "trials" if many or self.steps is None else "steps"
        return Cost(seconds + cells * PLOT_CELL_COST_S, option)

    def problems(self, given: frozenset[str] = frozenset()) -> list[dict[str, str]]:
        """A grid of more than ``MAX_CELLS`` cells, whatever its trials (its figures alone
        would take minutes and gigabytes), or of more than ``MAX_RUNS`` trials; an option
        ``given`` (named by the user, whatever its value) that the run does not take: a grid
        axis with a design stage that does not take it (the stages run their own conditions;
        only stage 4 takes ``backswing``), ``trials`` but 1 with ``nominal``, ``lr`` with SRD off,
        ``video`` with a design stage."""
        if self.stage is not None:
            ignored = ("inhibitor", "srd", "lr") if self.stage == 4 else GRID_AXES
            found = [
                {
                    "field": name,
                    "message": f"design stage {self.stage} runs its own conditions: it does not "
                    f"take {name}" + (" (stage 4 does)" if name == "backswing" else ""),
                }
                for name in (*ignored, *STAGE_ONLY_OF_GRID)
                if name in given
            ]
            if "video" in given:
                found.append(
                    {
                        "field": "video",
                        "message": f"design stage {self.stage} draws its own figures: it does not "
                        "take video",
                    }
                )
            least = STAGE2_SWING_FROM + STAGE2_WINDOW
            if self.stage == 2 and self.steps is not None and self.steps < least:
                found.append(
                    {
                        "field": "steps",
                        "message": f"design stage 2 swings the front thigh from step "
                        f"{STAGE2_SWING_FROM} and averages {STAGE2_WINDOW} steps after: give at "
                        f"least {least} steps",
                    }
                )
            return found
        found = []
        if self.nominal and "trials" in given and self.trials != 1:
            found.append(
                {
                    "field": "trials",
                    "message": "nominal runs one noise-free trial per condition: it takes no "
                    f"trials but 1 (given {self.trials})",
                }
            )
        if self.srd == "off" and "lr" in given:
            found.append(
                {"field": "lr", "message": "with srd off nothing is trained: it does not take lr"}
            )
        if found:
            return found
        cells = len(grid_conditions(self))
        if cells <= MAX_CELLS:
            runs = cells * (1 if self.nominal else self.trials)
            if runs <= MAX_RUNS:
                return []
            return [
                {
                    "field": "trials",
                    "message": f"the grid runs {runs} trials ({cells} cells × {self.trials}), at "
                    f"most {MAX_RUNS}: lower trials to at most {MAX_RUNS // cells}, or give "
                    "fewer grid values",
                }
            ]
        variants = cells // (len(self.backswing) * len(self.inhibitor))
        return [
            {
                "field": "backswing",
                "message": f"the grid has {cells} cells ({len(self.backswing)} backswing × "
                f"{len(self.inhibitor)} inhibitor × {variants} SRD variants), at most "
                f"{MAX_CELLS}: give fewer backswing, inhibitor or lr values",
            }
        ]


@dataclass(frozen=True)
class Condition:
    """One cell of the grid."""

    backswing: float
    inhibitor: float
    srd: bool
    lr: float | None


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
