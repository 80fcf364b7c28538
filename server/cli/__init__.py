"""The ``srd`` command line (typer). Each command lives in its own module of this package."""

from __future__ import annotations

import typer

app = typer.Typer(
    name="srd",
    help="Self Reward Design: fish sale auction service, screener and the paper's experiments.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    """Self Reward Design: fish sale auction service, screener and the paper's experiments."""


def _register() -> None:
    """Import the command modules; each adds its command(s) to ``app``."""
    import importlib

    for name in ("serve", "auction", "fish", "lavaland", "cheetah", "screen", "agents"):
        try:
            importlib.import_module(f"server.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"server.cli.{name}":
                raise


def main() -> None:
    """Console-script entry point."""
    _register()
    app()
