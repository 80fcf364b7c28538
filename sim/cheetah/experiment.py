"""The half-cheetah experiment: ``run`` (the main grid or a design stage), the grid's seeded
trials, their statistics and artifacts.

The grid is backswing × inhibitor × SRD (× learning rate) × trial; trial k's weight noise is
drawn from (seed, k), so every condition sees the same draw and SRD on/off are paired. The
grid's cells (condition, trial) are cut into units (``sim.units``) of ``CELLS_PER_UNIT``
consecutive cells, each stepped in one batch of the engine: a cell's numbers do not depend on
the other cells of its batch, so the units give the same numbers as one batch of every cell.
A design stage is one small run, made where the experiment is assembled (it has no units).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.cheetah_net import HalfCheetahSRD, noisy_fc_weight
from sim import units
from sim.cheetah.config import (
    Cells,
    condition_groups,
    condition_label,
    run_result,
)
from sim.cheetah.engine import HalfCheetahBatch, drive
from sim.cheetah.plots import plot_displacement, plot_lr_sweep
from sim.cheetah.render import render_gif
from sim.cheetah.stages import STAGES
from sim.cheetah.world import (
    CONTROL_INTERVAL,
    START_X,
    WARMUP_STEPS,
    evaluation_steps,
    inhibitor_active,
    relative_pose,
)
from sim.configs import TRIAL_STEPS, CheetahConfig, grid_conditions
from sim.experiment import ProgressFn, Stopwatch, no_progress, write_csv, write_json
from sim.units import Decomposition, Payload, Unit

CSV_STRIDE = 10
"""displacement.csv keeps every 10th step (0.1 s), and the last."""
CSV_FORMAT = ".6g"
"""Number format of displacement.csv (six significant digits keep it small)."""
SUMMARY_METRICS = ("final_displacement", "inhibited_abs_speed", "free_speed")
"""Per-trial numbers averaged per condition."""
CELLS_PER_UNIT = 35
"""Cells (condition, trial) stepped in one batch, one unit of the grid: large enough that the
per-step cost of the batched network is shared by many trials, small enough that the default
grid (140 cells) spreads over four workers."""


def run(
    config: CheetahConfig, *, out_dir: Path, progress: ProgressFn = no_progress
) -> dict[str, Any]:
    """Run the grid or a design stage here, write its artifacts into ``out_dir``, return the
    result."""
    return units.run(CELL_UNITS, config, out_dir=out_dir, progress=progress)


def trial_generator(seed: int, trial: int) -> torch.Generator:
    """The noise generator of trial ``trial``: the same draw in every condition (paired)."""
    state = np.random.SeedSequence([seed, trial]).generate_state(1, dtype=np.uint64)[0]
    return torch.Generator().manual_seed(int(state) & (2**63 - 1))


def grid_network(config: CheetahConfig, cells: Cells, trials: int) -> HalfCheetahSRD:
    """One HalfCheetahSRD over every trial of the grid: each trial's backswing, and its trial's
    noisy weights (the designed ones with ``nominal``)."""
    backswing = torch.tensor([c.backswing for c, _ in cells], dtype=torch.float32)
    if config.nominal:
        return HalfCheetahSRD(backswing)
    draws = noisy_fc_weight([trial_generator(config.seed, k) for k in range(trials)])
    return HalfCheetahSRD(backswing, fc_weight=draws[torch.tensor([k for _, k in cells])])


class GridController:
    """The grid's decisions: one batched network evaluation, with the SRD step of the trials
    that learn, counting the PFC's T verdicts and the decisions taken under the stop command."""

    def __init__(self, net: HalfCheetahSRD, cells: Cells) -> None:
        self.net = net
        self.inhibitor = torch.tensor([c.inhibitor for c, _ in cells], dtype=torch.float32)
        self.learns = torch.tensor([c.srd for c, _ in cells])
        self.lr = torch.tensor([c.lr or 0.0 for c, _ in cells], dtype=torch.float32)
        self.true_verdicts = torch.zeros(len(cells))
        """Per trial: decisions at which the PFC judged the action right (T ≥ F)."""
        self.judged = 0
        """Decisions at which the PFC judged (some trial learns)."""
        self.stopped: list[int] = []
        """Decision steps taken under the stop command."""

    def __call__(self, t: int, positions: np.ndarray) -> np.ndarray:
        u = torch.from_numpy(relative_pose(positions)).to(torch.float32)
        active = inhibitor_active(t)
        if active:
            self.stopped.append(t)
        actions, logits = self.net.act(
            u, self.inhibitor * float(active), srd=self.learns, lr=self.lr
        )
        if logits is not None:
            self.true_verdicts.add_((logits[:, 0] >= logits[:, 1]).float())
            self.judged += 1
        return actions.to(torch.float64).numpy()


def grid_cells(config: CheetahConfig) -> Cells:
    """Every cell of the grid, conditions in report order, then trials."""
    trials = 1 if config.nominal else config.trials
    return [(c, k) for c in grid_conditions(config) for k in range(trials)]


def plan_cells(config: CheetahConfig) -> list[Unit]:
    """Units of ``CELLS_PER_UNIT`` consecutive cells (none for a design stage)."""
    if config.stage is not None:
        return []
    n = len(grid_cells(config))
    return [
        Unit(
            f"cells {first + 1}-{min(first + CELLS_PER_UNIT, n)} of {n}",
            {"first": first, "count": min(CELLS_PER_UNIT, n - first)},
            weight=min(CELLS_PER_UNIT, n - first),
        )
        for first in range(0, n, CELLS_PER_UNIT)
    ]


def compute_cells(config: CheetahConfig, unit: Unit, progress: ProgressFn) -> Payload:
    """Step one unit's cells in one batch: their rows of runs.csv, torso x of every step,
    final weights, and the filmed trial's joint positions if it is one of them."""
    every = grid_cells(config)
    first, count = unit.spec["first"], unit.spec["count"]
    cells = every[first : first + count]
    steps = config.steps or TRIAL_STEPS
    net = grid_network(config, cells, 1 if config.nominal else config.trials)
    initial = [p.detach().clone() for p in net.parameters()]
    controller = GridController(net, cells)
    filmed = _video_trial(every) - first
    keep = filmed if config.video and 0 <= filmed < count else None
    with HalfCheetahBatch(len(cells), threads=config.threads) as batch:
        traj = drive(
            batch, steps, evaluation_steps(steps), controller, keep_qpos_of=keep, progress=progress
        )
    return {
        "runs": _grid_runs(cells, traj.torso_x, controller, initial, batch.timestep),
        "torso_x": traj.torso_x,
        "weights": [net.named_weights(i) for i in range(len(cells))],
        "qpos": traj.qpos,
        "timestep": batch.timestep,
    }


def assemble_cells(
    config: CheetahConfig,
    plan: Sequence[Unit],
    payloads: Sequence[Payload],
    *,
    out_dir: Path,
    progress: ProgressFn,
    watch: Stopwatch,
) -> dict[str, Any]:
    """The grid's statistics and artifacts from its units (a design stage runs here)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if config.stage is not None:
        return STAGES[config.stage](config, out_dir, progress)
    simulated_s = watch.elapsed()
    steps = config.steps or TRIAL_STEPS
    cells = grid_cells(config)
    runs = [row for p in payloads for row in p["runs"]]
    torso_x = np.concatenate([p["torso_x"] for p in payloads])
    weights = [w for p in payloads for w in p["weights"]]
    timestep = payloads[0]["timestep"]
    displacement = torso_x - torso_x[:, :1]
    summary = summarise(runs)
    progress(0.2, "writing artifacts")
    artifacts = _write_grid_artifacts(out_dir, runs, summary, cells, displacement, weights)
    progress(0.3, "drawing the figures")
    figure = plot_displacement(out_dir / "displacement.png", cells, displacement, timestep)
    artifacts.append(figure.name)
    if len(config.lr) > 1 and config.srd == "both":
        artifacts.append(plot_lr_sweep(out_dir / "lr_sweep.png", runs).name)
    video: dict[str, Any] = {"video": None, "video_note": "video off (--no-video)"}
    qpos = next((p["qpos"] for p in payloads if p["qpos"] is not None), None)
    if config.video and qpos is not None:
        cond, k = cells[_video_trial(cells)]
        label = f"b{cond.backswing:g} i{cond.inhibitor:g} srd {'on' if cond.srd else 'off'}"
        progress(0.4, "rendering the GIF")
        video = render_gif(out_dir / "cheetah.gif", qpos, START_X, f"{label} trial {k + 1}")
        if video["video"]:
            artifacts.append(video["video"])
    fields = {
        "trials": 1 if config.nominal else config.trials,
        "steps": steps,
        "n_runs": len(cells),
        "runs": runs,
        "summary": summary,
        "simulated_steps": len(cells) * steps,
        "simulation_s": simulated_s,
        **video,
    }
    return run_result(config, fields, artifacts, watch)


CELL_UNITS = Decomposition(plan_cells, compute_cells, assemble_cells)
"""The grid cut into batches of cells."""


def _grid_runs(
    cells: Cells,
    torso_x: np.ndarray,
    controller: GridController,
    initial: list[torch.Tensor],
    timestep: float,
) -> list[dict[str, Any]]:
    """One row per trial: its condition, displacement, speeds, verdicts and weight changes."""
    displacement = torso_x[:, -1] - torso_x[:, 0]
    stopped_steps = _held_steps(controller.stopped, torso_x.shape[1])
    speeds = _speeds(torso_x, stopped_steps, timestep)
    controller_change, pfc_change = _parameter_changes(controller.net, initial)
    judged = controller.judged
    return [
        {
            "backswing": cond.backswing,
            "inhibitor": cond.inhibitor,
            "srd": "on" if cond.srd else "off",
            "lr": cond.lr,
            "trial": k + 1,
            "final_displacement": float(displacement[index]),
            "inhibited_abs_speed": speeds["inhibited"][index],
            "free_speed": speeds["free"][index],
            "true_verdict_fraction": (
                float(controller.true_verdicts[index]) / judged if cond.srd and judged else None
            ),
            "controller_change": controller_change[index],
            "pfc_change": pfc_change[index],
        }
        for index, (cond, k) in enumerate(cells)
    ]


def _video_trial(cells: Cells) -> int:
    """The trial to film: the first with inhibitor > 0 (it runs and stops), else the first."""
    return next((i for i, (c, _) in enumerate(cells) if c.inhibitor > 0), 0)


def _held_steps(evaluations: list[int], steps: int) -> np.ndarray:
    """Boolean (steps,) mask of the steps whose control came from the given evaluations."""
    mask = np.zeros(steps, dtype=bool)
    for t in evaluations:
        mask[t + 1 : t + 1 + CONTROL_INTERVAL] = True
    return mask


def _speeds(torso_x: np.ndarray, inhibited: np.ndarray, timestep: float) -> dict[str, list[Any]]:
    """Per trial: mean |x velocity| over the stop-command steps, mean x velocity elsewhere.

    The velocity of step t is (x[t + 1] − x[t]) / 0.01 s; "elsewhere" counts the steps after
    the first network evaluation only (the landing is not running).
    """
    velocity = np.diff(torso_x, axis=1) / timestep
    inhibited = inhibited[: velocity.shape[1]]
    free = ~inhibited
    free[: WARMUP_STEPS + 2] = False

    def mean_over(mask: np.ndarray, values: np.ndarray) -> list[float | None]:
        if not mask.any():
            return [None] * values.shape[0]
        return [float(v) for v in values[:, mask].mean(axis=1)]

    return {"inhibited": mean_over(inhibited, np.abs(velocity)), "free": mean_over(free, velocity)}


def _parameter_changes(
    net: HalfCheetahSRD, initial: list[torch.Tensor]
) -> tuple[list[float], list[float]]:
    """Largest |Δ| per trial over the controller's and over the PFC's parameters."""
    before = dict(zip((id(p) for p in net.parameters()), initial, strict=True))

    def largest(params: list[torch.Tensor]) -> list[float]:
        deltas = [(p.detach() - before[id(p)]).abs().reshape(net.n_trials, -1) for p in params]
        return torch.cat(deltas, dim=1).max(dim=1).values.tolist()

    return largest(net.controller_parameters()), largest(net.pfc_parameters())


def summarise(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean and (sample) SD of each metric per condition (backswing, inhibitor, srd, lr)."""
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in runs:
        groups.setdefault((r["backswing"], r["inhibitor"], r["srd"], r["lr"]), []).append(r)
    rows = []
    for (b, i, srd, lr), members in groups.items():
        row: dict[str, Any] = {"backswing": b, "inhibitor": i, "srd": srd, "lr": lr}
        row["n"] = len(members)
        for metric in SUMMARY_METRICS:
            values = np.array([m[metric] for m in members if m[metric] is not None], dtype=float)
            row[f"mean_{metric}"] = float(values.mean()) if values.size else None
            # the sample's SD: none of fewer than two values (one trial, or none measured)
            row[f"sd_{metric}"] = float(values.std(ddof=1)) if values.size > 1 else None
        rows.append(row)
    return rows


def _write_grid_artifacts(
    out_dir: Path,
    runs: list[dict[str, Any]],
    summary: list[dict[str, Any]],
    cells: Cells,
    displacement: np.ndarray,
    weights: list[dict[str, float]],
) -> list[str]:
    """runs.csv, summary.csv, displacement.csv (condition means/SD every 0.1 s), weights.json."""
    names = [write_csv(out_dir / "runs.csv", runs), write_csv(out_dir / "summary.csv", summary)]
    last = displacement.shape[1] - 1  # kept too: the final displacement is runs.csv's
    steps = np.unique(np.append(np.arange(0, last + 1, CSV_STRIDE), last))
    columns: dict[str, np.ndarray] = {"step": steps}
    for cond, index in condition_groups(cells).items():
        tag = f"b{cond.backswing:g}_i{cond.inhibitor:g}_" + (
            f"srd_lr{cond.lr:g}" if cond.srd else "nosrd"
        )
        values = displacement[index][:, steps]
        columns[f"mean_{tag}"] = values.mean(axis=0)
        spread = values.std(axis=0, ddof=1) if len(index) > 1 else np.zeros(values.shape[1])
        columns[f"sd_{tag}"] = spread
    table = np.column_stack(list(columns.values()))
    rows = [dict(zip(columns, (f"{v:{CSV_FORMAT}}" for v in line), strict=True)) for line in table]
    names.append(write_csv(out_dir / "displacement.csv", rows))
    weights = [
        {"condition": condition_label(c), "backswing": c.backswing, "trial": k + 1}
        | {"final_weights": final}
        for (c, k), final in zip(cells, weights, strict=True)
    ]
    write_json(out_dir / "weights.json", weights)
    names.append("weights.json")
    return names
