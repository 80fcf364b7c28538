"""``srd fish``: the robot fish 1D experiment (sim.fish)."""

from __future__ import annotations

from pathlib import Path

import typer

from server.cli import app
from server.cli.common import JsonOption, OutOption, SeedOption, execute


@app.command()
def fish(
    steps: int = typer.Option(12000, "--steps", help="Simulation steps."),
    srd: bool = typer.Option(True, "--srd/--no-srd", help="Self-reward training on/off."),
    memory: int = typer.Option(8, "--memory", help="Steps of PFC verdicts summed per update."),
    lr: float = typer.Option(0.002, "--lr", help="Adam learning rate of the SRD updates."),
    average_every: int = typer.Option(
        24, "--average-every", help="Window (steps) of the figure's averaged-energy panel."
    ),
    seed: int = SeedOption,
    out: Path | None = OutOption,
    json_output: bool = JsonOption,
) -> None:
    """Robot fish 1D (paper: 'Robot fish: 1D toy example'): energy with and without SRD."""
    execute(
        "fish",
        "fish",
        {
            "steps": steps,
            "srd": srd,
            "memory": memory,
            "lr": lr,
            "average_every": average_every,
            "seed": seed,
        },
        out=out,
        json_output=json_output,
    )
