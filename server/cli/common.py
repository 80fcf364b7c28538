"""What every experiment command shares: output folder, progress bar, ``--json`` output."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from sim.experiment import ConfigError, default_out_dir, parse_config, write_json
from sim.registry import KINDS

stderr = Console(stderr=True)

SeedOption = typer.Option(0, "--seed", help="Random seed: same seed, same numbers.")
OutOption = typer.Option(
    None, "--out", help="Artifacts folder (default runs/<command>__<seed>__<time>/)."
)
JsonOption = typer.Option(False, "--json", help="Print exactly one JSON object on stdout.")


def execute(
    kind: str, command: str, params: dict[str, Any], *, out: Path | None, json_output: bool
) -> dict[str, Any]:
    """Validate ``params`` into the kind's config, run it with a progress bar, print the result.

    Exits with code 2 and a message naming the option when an option is invalid.
    """
    try:
        config_cls, runner = KINDS[kind].load()
        config = parse_config(config_cls, params)
    except ConfigError as exc:
        for err in exc.errors:
            stderr.print(f"[red]error:[/red] --{err['field'].replace('_', '-')}: {err['message']}")
        raise typer.Exit(code=2) from exc
    out_dir = out or default_out_dir(command, int(params.get("seed", 0)))
    out_dir.mkdir(parents=True, exist_ok=True)
    show_bar = sys.stderr.isatty()
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        TextColumn("{task.fields[message]}"),
        console=stderr,
        disable=not show_bar,
        transient=False,
    ) as bar:
        task = bar.add_task(command, total=1.0, message="")

        def progress(fraction: float, message: str) -> None:
            bar.update(task, completed=min(max(fraction, 0.0), 1.0), message=message)

        result: dict[str, Any] = runner(config, out_dir=out_dir, progress=progress)
        progress(1.0, "done")
    write_json(out_dir / "result.json", result)
    if json_output:
        sys.stdout.write(json.dumps(result) + "\n")
    else:
        stderr.print(json.dumps(result, indent=2))
        stderr.print(f"artifacts: {out_dir}")
    return result
