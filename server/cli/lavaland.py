"""``srd lavaland``: Robot2NN in lavaland (paper, "2D robot lavaland", Table 1)."""

from __future__ import annotations

from pathlib import Path

import typer

from server.cli import app
from server.cli.common import JsonOption, OutOption, SeedOption, execute


@app.command()
def lavaland(
    project: str = typer.Option("A", help="Project: A, compare-A, lava-A or lava-noav-A."),
    preset: str = typer.Option(
        "paper", help="paper (4 plans, best executed) or reference (the v1 code, Table 1)."
    ),
    eval_maps: int = typer.Option(4096, help="Evaluation maps."),
    train_maps: int = typer.Option(4096, help="Training maps, one SGD step each; 0 skips SRD."),
    repeats: int = typer.Option(1, help="Independent experiments (the paper's expts 1-4)."),
    n_plans: int = typer.Option(0, help="Imagined plans per map; 0 = the preset's."),
    lr: float = typer.Option(1e-4, help="SGD learning rate."),
    gif_map: int = typer.Option(0, help="Evaluation map animated in trajectory.gif."),
    seed: int = SeedOption,
    out: Path | None = OutOption,
    json_output: bool = JsonOption,
) -> None:
    """Evaluate the untrained robot, SRD-train it one epoch, evaluate again."""
    execute(
        "lavaland",
        "lavaland",
        {
            "project": project,
            "preset": preset,
            "eval_maps": eval_maps,
            "train_maps": train_maps,
            "repeats": repeats,
            "n_plans": n_plans,
            "lr": lr,
            "gif_map": gif_map,
            "seed": seed,
        },
        out=out,
        json_output=json_output,
    )
