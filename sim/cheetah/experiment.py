"""The half-cheetah experiment: ``run`` (the main grid or a design stage), the grid's seeded
trials, their statistics and artifacts.

The grid is backswing × inhibitor × SRD (× learning rate) × trial, every trial in one batch of
the engine; trial k's weight noise is drawn from (seed, k), so every condition sees the same
draw and SRD on/off are paired.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.cheetah_net import HalfCheetahSRD, noisy_fc_weight
from sim.cheetah.config import (
    Cells,
    CheetahConfig,
    condition_groups,
    condition_label,
    grid_conditions,
    run_result,
)
from sim.cheetah.engine import HalfCheetahBatch, drive
from sim.cheetah.plots import plot_displacement, plot_lr_sweep
from sim.cheetah.render import render_gif
from sim.cheetah.stages import STAGES
from sim.cheetah.world import (
    CONTROL_INTERVAL,
    START_X,
    TRIAL_STEPS,
    WARMUP_STEPS,
    evaluation_steps,
    inhibitor_active,
    relative_pose,
)
from sim.experiment import ProgressFn, Stopwatch, no_progress, write_csv, write_json

CSV_STRIDE = 10
"""displacement.csv keeps every 10th step (0.1 s)."""
CSV_FORMAT = ".6g"
"""Number format of displacement.csv (six significant digits keep it small)."""
SIMULATION_SHARE = 0.95
"""Share of the progress bar given to the simulation (the rest: statistics and artifacts)."""
SUMMARY_METRICS = ("final_displacement", "inhibited_abs_speed", "free_speed")
"""Per-trial numbers averaged per condition."""


def run(
    config: CheetahConfig, *, out_dir: Path, progress: ProgressFn = no_progress
) -> dict[str, Any]:
    """Run the grid or a design stage, write its artifacts into ``out_dir``, return the result."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if config.stage is not None:
        return STAGES[config.stage](config, out_dir, progress)
    return run_grid(config, out_dir=out_dir, progress=progress)


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


def run_grid(
    config: CheetahConfig, *, out_dir: Path, progress: ProgressFn = no_progress
) -> dict[str, Any]:
    """The main experiment: every trial of every condition in one batch."""
    watch = Stopwatch()
    steps = config.steps or TRIAL_STEPS
    trials = 1 if config.nominal else config.trials
    cells = [(c, k) for c in grid_conditions(config) for k in range(trials)]
    net = grid_network(config, cells, trials)
    initial = [p.detach().clone() for p in net.parameters()]
    controller = GridController(net, cells)
    video_trial = _video_trial(cells)
    with HalfCheetahBatch(len(cells), threads=config.threads) as batch:
        traj = drive(
            batch,
            steps,
            evaluation_steps(steps),
            controller,
            keep_qpos_of=video_trial if config.video else None,
            progress=lambda f, m: progress(SIMULATION_SHARE * f, m),
        )
    simulated_s = watch.elapsed()
    displacement = traj.torso_x - traj.torso_x[:, :1]
    runs = _grid_runs(cells, traj.torso_x, controller, initial, batch.timestep)
    summary = summarise(runs)
    progress(0.96, "writing artifacts")
    artifacts = _write_grid_artifacts(out_dir, runs, summary, cells, displacement, net)
    figure = plot_displacement(out_dir / "displacement.png", cells, displacement, batch.timestep)
    artifacts.append(figure.name)
    if len(config.lr) > 1 and config.srd == "both":
        artifacts.append(plot_lr_sweep(out_dir / "lr_sweep.png", runs).name)
    video: dict[str, Any] = {"video": None, "video_note": "video off (--no-video)"}
    if config.video and traj.qpos is not None:
        cond, k = cells[video_trial]
        label = f"b{cond.backswing:g} i{cond.inhibitor:g} srd {'on' if cond.srd else 'off'}"
        progress(0.97, "rendering the GIF")
        video = render_gif(out_dir / "cheetah.gif", traj.qpos, START_X, f"{label} trial {k + 1}")
        if video["video"]:
            artifacts.append(video["video"])
    fields = {
        "trials": trials,
        "steps": steps,
        "n_runs": len(cells),
        "runs": runs,
        "summary": summary,
        "simulated_steps": len(cells) * steps,
        "simulation_s": simulated_s,
        **video,
    }
    return run_result(config, fields, artifacts, watch)


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
            row[f"sd_{metric}"] = float(values.std(ddof=1)) if values.size > 1 else 0.0
        rows.append(row)
    return rows


def _write_grid_artifacts(
    out_dir: Path,
    runs: list[dict[str, Any]],
    summary: list[dict[str, Any]],
    cells: Cells,
    displacement: np.ndarray,
    net: HalfCheetahSRD,
) -> list[str]:
    """runs.csv, summary.csv, displacement.csv (condition means/SD every 0.1 s), weights.json."""
    names = [write_csv(out_dir / "runs.csv", runs), write_csv(out_dir / "summary.csv", summary)]
    stride = CSV_STRIDE
    columns = {"step": np.arange(0, displacement.shape[1], stride)}
    for cond, index in condition_groups(cells).items():
        tag = f"b{cond.backswing:g}_i{cond.inhibitor:g}_" + (
            f"srd_lr{cond.lr:g}" if cond.srd else "nosrd"
        )
        values = displacement[index][:, ::stride]
        columns[f"mean_{tag}"] = values.mean(axis=0)
        columns[f"sd_{tag}"] = values.std(axis=0, ddof=1) if len(index) > 1 else 0 * values[0]
    table = np.column_stack(list(columns.values()))
    rows = [dict(zip(columns, (f"{v:{CSV_FORMAT}}" for v in line), strict=True)) for line in table]
    names.append(write_csv(out_dir / "displacement.csv", rows))
    weights = [
        {"condition": condition_label(c), "backswing": c.backswing, "trial": k + 1}
        | {"final_weights": net.named_weights(i)}
        for i, (c, k) in enumerate(cells)
    ]
    write_json(out_dir / "weights.json", weights)
    names.append("weights.json")
    return names
