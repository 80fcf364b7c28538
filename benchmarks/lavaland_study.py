"""The lavaland repeat study: every project × preset, the paper's loss and the guarded loss,
10 repeats each, through ``sim.lavaland.run`` (each run's folder holds its job artifacts:
summary.csv, repeats.png, accuracy.csv ...).

Writes ``study.csv`` (one summary row per run) in the output folder, the figure
``docs/figures/lavaland_repeat_study.png``, and prints the table of docs/lavaland.md.

    .venv/bin/python benchmarks/lavaland_study.py [--repeats 10] [--out runs/lavaland_study]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import torch

from agents.planning import PRESETS
from sim.experiment import pyplot, write_csv
from sim.lavaland import LavalandConfig, run
from sim.lavaland.engine import PROJECTS

FIGURE = Path("docs/figures/lavaland_repeat_study.png")


def plot(path: Path, runs: dict[tuple[str, str, bool], list[dict[str, Any]]]) -> None:
    """One panel per project × preset: every repeat before SRD and after it, both losses."""
    plt = pyplot()
    fig, axes = plt.subplots(
        len(PRESETS), len(PROJECTS), figsize=(3.0 * len(PROJECTS), 2.7 * len(PRESETS)), dpi=100
    )
    for row, preset in enumerate(PRESETS):
        for column, project in enumerate(PROJECTS):
            ax = axes[row, column]
            for guard, colour, label in (
                (False, "tab:red", "paper loss"),
                (True, "tab:blue", "guarded"),
            ):
                repeats = runs[project, preset, guard]
                x = [r["repeat"] for r in repeats]
                if not guard:
                    ax.plot(
                        x,
                        [r["accuracy_untrained"] for r in repeats],
                        "o",
                        color="tab:gray",
                        label="no SRD",
                    )
                ax.plot(
                    x,
                    [r["accuracy_srd"] for r in repeats],
                    "o-",
                    color=colour,
                    lw=0.8,
                    ms=4,
                    label=f"SRD, {label}",
                )
            ax.set_title(f"{project}, {preset}", fontsize=9)
            ax.set_ylim(0.3, 1.0)
            ax.set_xticks(x)
            ax.tick_params(labelsize=7)
            if column == 0:
                ax.set_ylabel("accuracy")
            if row == len(PRESETS) - 1:
                ax.set_xlabel("repeat")
    axes[0, 0].legend(loc="lower left", fontsize=7)
    fig.suptitle("Lavaland: accuracy of every repeat, before SRD and after it", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("runs/lavaland_study"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    summaries, runs = [], {}
    for preset in PRESETS:
        for project in PROJECTS:
            for guard in (False, True):
                config = LavalandConfig(
                    project=project,
                    preset=preset,
                    loss_guard=guard,
                    repeats=args.repeats,
                )
                folder = args.out / f"{project}_{preset}_{'guarded' if guard else 'paper-loss'}"
                result = run(config, out_dir=folder)
                summaries.append(result["summary"])
                runs[project, preset, guard] = result["repeats"]
                print(f"{folder}: {result['elapsed_s']:.0f} s", flush=True)
    write_csv(args.out / "study.csv", summaries)
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    plot(FIGURE, runs)
    print("| project | preset | loss | no SRD mean (min) | SRD mean | SRD min | lowered | worst |")
    print("|---|---|---|---|---|---|---|---|")
    for s in summaries:
        print(
            f"| {s['project']} | {s['preset']} | {'guarded' if s['loss_guard'] else 'paper'} "
            f"| {s['mean_untrained']:.3f} ({s['min_untrained']:.3f}) | {s['mean_srd']:.3f} "
            f"| {s['min_srd']:.3f} | {100 * s['lowered_share']:.0f} % | {s['worst_change']:+.3f} |"
        )


if __name__ == "__main__":
    main()
