"""``srd cheetah``: HalfCheetahSRD in MuJoCo, the whole grid in one batch (sim.cheetah)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from server.cli import app
from server.cli.common import JsonOption, OutOption, SeedOption, execute


@app.command()
def cheetah(
    backswing: str = typer.Option(
        "1,2,3,4,5", "--backswing", help="BS neuron gains, comma-separated."
    ),
    inhibitor: str = typer.Option(
        "0,2", "--inhibitor", help="Stop-command inhibitor values, comma-separated."
    ),
    srd: str = typer.Option("both", "--srd", help="Self-reward optimisation: on, off or both."),
    trials: int = typer.Option(7, "--trials", help="Seeded trials per condition."),
    steps: int | None = typer.Option(
        None, "--steps", help="Steps of 0.01 s (default 3600; stages 400 / 1200)."
    ),
    nominal: bool = typer.Option(
        False, "--nominal", help="Noise-free designed weights (one trial per condition)."
    ),
    stage: int | None = typer.Option(
        None, "--stage", help="Run design stage 0..4 of the appendix instead of the grid."
    ),
    lr: str = typer.Option(
        "1e-4", "--lr", help="SRD learning rate(s); several (1e-4,1e-2) sweep them."
    ),
    threads: int = typer.Option(2, "--threads", help="Threads stepping MuJoCo."),
    video: bool = typer.Option(
        True, "--video/--no-video", help="GIF of one trial (needs offscreen OpenGL)."
    ),
    seed: int = SeedOption,
    out: Path | None = OutOption,
    json_output: bool = JsonOption,
) -> None:
    """Half-cheetah with SRD (paper: 'MuJoCo with SRD'): run, stop on command, mean x ± SD."""
    params: dict[str, Any] = {
        "backswing": backswing,
        "inhibitor": inhibitor,
        "srd": srd,
        "trials": trials,
        "nominal": nominal,
        "lr": lr,
        "threads": threads,
        "video": video,
        "seed": seed,
    }
    if steps is not None:
        params["steps"] = steps
    if stage is not None:
        params["stage"] = stage
    execute("cheetah", "cheetah", params, out=out, json_output=json_output)
