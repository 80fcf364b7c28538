"""``srd auction-study``: the paper's price-vs-supply grid without HTTP (sim.studies)."""

from __future__ import annotations

from pathlib import Path

import typer

from server.cli import app
from server.cli.common import JsonOption, OutOption, SeedOption, execute


@app.command("auction-study")
def auction_study(
    rarities: str = typer.Option(
        "0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9",
        "--rarities",
        help="Item supplies r, comma-separated; fish on sale = int(r · patrons).",
    ),
    trials: int = typer.Option(10, "--trials", help="Independent auctions per supply."),
    patrons: int = typer.Option(64, "--patrons", help="Patrons per auction, saboteurs included."),
    fine_tune: bool = typer.Option(
        False, "--fine-tune/--no-fine-tune", help="Patrons fine-tune themselves (SRD)."
    ),
    saboteurs: float = typer.Option(
        0.0, "--saboteurs", help="Fraction of always-hold saboteurs (the last patrons)."
    ),
    screen: bool = typer.Option(
        False, "--screen/--no-screen", help="Screen every patron; refused ones stay out."
    ),
    grid: bool = typer.Option(
        False,
        "--grid",
        help="The paper's whole grid: fine-tune off/on × saboteurs 0 and (--saboteurs or 0.5).",
    ),
    max_iterations: int = typer.Option(64, "--max-iterations", help="Iterations per auction."),
    fine_tune_rounds: int = typer.Option(
        4, "--fine-tune-rounds", help="Fine-tuning after each of the first N iterations."
    ),
    seed: int = SeedOption,
    out: Path | None = OutOption,
    json_output: bool = JsonOption,
) -> None:
    """Fish sale auctions without HTTP: purchase price and rate vs item supply (Fig. C/D)."""
    execute(
        "auction-study",
        "auction-study",
        {
            "rarities": rarities,
            "trials": trials,
            "patrons": patrons,
            "fine_tune": fine_tune,
            "saboteurs": saboteurs,
            "screen": screen,
            "grid": grid,
            "max_iterations": max_iterations,
            "fine_tune_rounds": fine_tune_rounds,
            "seed": seed,
        },
        out=out,
        json_output=json_output,
    )
