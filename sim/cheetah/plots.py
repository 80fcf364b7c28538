"""The half-cheetah's figures: grid displacement, the SRD learning-rate study, the design
stages' line plots and the stage-1 resting pose."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from sim.cheetah.config import Cells, Condition, condition_groups, condition_label
from sim.cheetah.world import FLOOR_Z, stop_windows
from sim.experiment import pyplot

FIGURE_DPI = 80
"""Keeps the figures small."""
PLOT_STRIDE = 5
"""Plot every 5th step (0.05 s), and the last: the curves look the same and draw faster."""
MIN_WIDTH = 7.5
"""Inches: the displacement figure's least width, that of its title (one inhibitor value
had cut it on both sides)."""


def plot_displacement(path: Path, cells: Cells, displacement: np.ndarray, timestep: float) -> Path:
    """Mean displacement ± SD over trials against time, one line per backswing.

    Rows: SRD variants (on first, as the reference plots them), columns: inhibitor values.
    """
    plt = pyplot()
    groups = condition_groups(cells)
    variants = list(dict.fromkeys((c.srd, c.lr) for c in groups))
    inhibitors = list(dict.fromkeys(c.inhibitor for c in groups))
    backswings = list(dict.fromkeys(c.backswing for c in groups))
    fig, axes = plt.subplots(
        len(variants),
        len(inhibitors),
        figsize=(max(4.2 * len(inhibitors), MIN_WIDTH), 2.8 * len(variants)),  # the title fits
        sharex=True,
        sharey=True,
        squeeze=False,
    )
    steps = displacement.shape[1]  # every PLOT_STRIDE-th step, and the last: where it ends
    shown = np.unique(np.r_[np.arange(0, steps, PLOT_STRIDE), steps - 1])
    time = shown * timestep
    colours = plt.get_cmap("viridis")(np.linspace(0, 0.9, len(backswings)))
    for row, (srd, lr) in enumerate(variants):
        for col, inh in enumerate(inhibitors):
            ax = axes[row][col]
            for colour, b in zip(colours, backswings, strict=True):
                index = groups[Condition(b, inh, srd, lr)]
                values = displacement[index][:, shown]
                mean = values.mean(axis=0)
                sd = values.std(axis=0, ddof=1) if len(index) > 1 else 0 * mean
                ax.plot(time, mean, color=colour, lw=1.2, label=f"backswing {b:g}")
                ax.fill_between(time, mean - sd, mean + sd, color=colour, alpha=0.2, lw=0)
            if inh > 0:
                for lo, hi in stop_windows(displacement.shape[1]):
                    ax.axvspan(lo * timestep, hi * timestep, color="0.85", zorder=0)
            ax.set_title(condition_label(Condition(0, inh, srd, lr)), fontsize=9)
            ax.grid(alpha=0.3)
            if row == len(variants) - 1:
                ax.set_xlabel("time (s)")
            if col == 0:
                ax.set_ylabel("x displacement (m)")
    axes[0][0].legend(fontsize=7, loc="upper left")
    n_trials = max(len(v) for v in groups.values())
    fig.suptitle(
        f"HalfCheetahSRD: mean torso x displacement ± SD over {n_trials} trial(s)"
        " (grey: stop command)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=FIGURE_DPI)
    plt.close(fig)
    return path


def plot_lr_sweep(path: Path, runs: list[dict[str, Any]]) -> Path:
    """SRD's effect against its learning rate, paired with the SRD-off twin of each trial.

    Left: standing still under the stop command (mean |x velocity| in the stop windows,
    inhibitor > 0). Right: running (mean x velocity outside the windows, inhibitor 0).
    Points: mean over trials and backswings of (SRD on − SRD off), bars: ± SD.
    """
    plt = pyplot()
    off = {(r["backswing"], r["inhibitor"], r["trial"]): r for r in runs if r["srd"] == "off"}
    lrs = sorted({r["lr"] for r in runs if r["srd"] == "on"})
    panels = (
        ("inhibited_abs_speed", lambda i: i > 0, "stop windows: Δ mean |vx| (m/s)"),
        ("free_speed", lambda i: i == 0, "running: Δ mean vx (m/s)"),
    )
    fig, axes = plt.subplots(1, 2, figsize=(8.4, 3.0))
    for ax, (metric, pick, title) in zip(axes, panels, strict=True):
        baseline = [r[metric] for r in off.values() if pick(r["inhibitor"]) and r[metric]]
        if baseline:
            spread = f" ± {np.std(baseline, ddof=1):.3f}" if len(baseline) > 1 else ""
            title += f"\nSRD off: {np.mean(baseline):.3f}{spread}"
        means, sds = [], []
        for lr in lrs:
            diffs = [
                r[metric] - off[(r["backswing"], r["inhibitor"], r["trial"])][metric]
                for r in runs
                if r["srd"] == "on" and r["lr"] == lr and pick(r["inhibitor"])
                if r[metric] is not None
            ]
            means.append(float(np.mean(diffs)) if diffs else math.nan)
            sds.append(float(np.std(diffs, ddof=1)) if len(diffs) > 1 else 0.0)
        ax.axhline(0.0, color="0.5", lw=0.8)
        if all(math.isnan(m) for m in means):  # no such cells, or runs too short to tell
            ax.text(0.5, 0.5, "nothing measured", ha="center", va="center", transform=ax.transAxes)
            ax.set_xticks([])
            ax.set_yticks([])
        else:
            ax.errorbar(lrs, means, yerr=sds, marker="o", capsize=3)
            ax.set_xscale("log")
        ax.set_xlabel("SRD learning rate")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle("SRD on minus SRD off, same initial weights (mean ± SD over trials)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=FIGURE_DPI)
    plt.close(fig)
    return path


def plot_lines(
    path: Path,
    time: np.ndarray,
    series: list[tuple[str, np.ndarray]],
    *,
    title: str,
    ylabel: str,
    extra: list[tuple[str, np.ndarray]] | None = None,
    extra_ylabel: str = "",
) -> Path:
    """One or two stacked panels of labelled lines against time."""
    plt = pyplot()
    panels = [(series, ylabel)] + ([(extra, extra_ylabel)] if extra else [])
    fig, axes = plt.subplots(len(panels), 1, figsize=(7.0, 2.6 * len(panels)), squeeze=False)
    for ax, (lines, label) in zip(axes[:, 0], panels, strict=True):
        for name, values in lines:
            ax.plot(time, values, lw=1.1, label=name)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=3)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=FIGURE_DPI)
    plt.close(fig)
    return path


def plot_rest_pose(path: Path, rest: np.ndarray) -> Path:
    """The seven body origins (7, 3) of the resting cheetah, torso → each leg, in the x-z plane."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.0, 3.0))
    ax.plot(rest[:4, 0], rest[:4, 2], "o-", label="torso → back leg")
    ax.plot(rest[[0, 4, 5, 6], 0], rest[[0, 4, 5, 6], 2], "o-", label="torso → front leg")
    for i, (x, z) in enumerate(rest[:, [0, 2]]):
        ax.annotate(f"{i}", (x, z), textcoords="offset points", xytext=(3, 3), fontsize=8)
    ax.axhline(FLOOR_Z, color="0.5", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title("Stage 1: resting pose (0 torso … 6 front foot)", fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=FIGURE_DPI)
    plt.close(fig)
    return path
