"""``srd screen FILE``: screen one FSN manifest (exit 0 accepted, 1 rejected, 2 malformed)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.markup import escape

from agents.manifest import ManifestError, parse_manifest_json
from screener import screen as screen_manifest
from server.cli import app
from server.cli.common import JsonOption

ACCEPTED, REJECTED, MALFORMED = 0, 1, 2
"""Exit codes (INTERFACE.md)."""
FileArgument = typer.Argument(..., help="The manifest (JSON) to screen.")


def _emit(obj: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")


def _malformed(errors: list[dict[str, str]], json_output: bool) -> typer.Exit:
    err = Console(stderr=True)
    for e in errors:
        err.print(f"[red]error:[/red] {escape(e['path'])}: {escape(e['message'])}", highlight=False)
    if json_output:
        _emit({"accepted": False, "reasons": [], "errors": errors})
    return typer.Exit(code=MALFORMED)


@app.command()
def screen(
    file: Path = FileArgument,
    json_output: bool = JsonOption,
) -> None:
    """Screen a Fish Sale Negotiator manifest: semantic rules on its named weights and
    behavioural probes. Exit 0 accepted, 1 rejected, 2 unreadable or malformed."""
    try:
        text = file.read_bytes()
    except OSError as exc:
        raise _malformed([{"path": "$", "message": f"cannot read {file}: {exc.strerror}"}],
                         json_output) from exc  # fmt: skip
    try:
        manifest = parse_manifest_json(text)
    except ManifestError as exc:
        raise _malformed(exc.errors, json_output) from exc
    verdict = screen_manifest(manifest)
    if json_output:
        _emit(verdict.to_dict())
    else:
        out = Console(highlight=False, soft_wrap=True)
        word = "[green]accepted[/green]" if verdict.accepted else "[red]rejected[/red]"
        out.print(f"{escape(manifest.participant)}: {word}")
        for reason in verdict.reasons:
            out.print(f"  [bold]{reason.neuron}[/bold] ({reason.rule}): {escape(reason.message)}")
    raise typer.Exit(code=ACCEPTED if verdict.accepted else REJECTED)
