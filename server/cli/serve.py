"""``srd serve``: run the auction house API with uvicorn."""

from __future__ import annotations

import logging

import click

UNUSABLE = 2
"""The exit code of a server that cannot start with its settings (its data folder)."""


@click.command("serve")
@click.option("--host", default=None, help="Bind address [default: SRD_HOST or 127.0.0.1].")
@click.option(
    "--port", type=click.IntRange(0, 65535), default=None, help="Port [default: SRD_PORT or 8000]."
)
@click.option(
    "--log-level",
    type=click.Choice(["critical", "error", "warning", "info", "debug"]),
    default="info",
    show_default=True,
    help="uvicorn log level.",
)
def command(host: str | None, port: int | None, log_level: str) -> None:
    """Run the HTTP API; database from SRD_DATABASE_URL (default sqlite:///./srd.db). Exits
    with code 2, saying why, when the data folder (SRD_DATA_DIR) cannot be written."""
    import uvicorn

    from server.app import create_app
    from server.config import get_settings
    from server.readiness import make_data_dir
    from server.remote_rounds.sockets import MAX_FRAME_BYTES

    settings = get_settings()
    problem = make_data_dir(settings.data_dir)
    if problem is not None:
        click.echo(f"srd serve: {problem} (SRD_DATA_DIR)", err=True)
        raise SystemExit(UNUSABLE)
    logging.basicConfig(level=log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    uvicorn.run(
        create_app(settings),
        host=host or settings.host,
        port=settings.port if port is None else port,
        log_level=log_level,
        access_log=settings.access_log,
        timeout_graceful_shutdown=10,
        ws_max_size=MAX_FRAME_BYTES,  # the round sockets' frames (an upload's manifest)
    )
