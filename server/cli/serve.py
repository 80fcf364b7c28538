"""``srd serve``: run the auction house API with uvicorn."""

from __future__ import annotations

import logging

import typer
import uvicorn

from server.app import create_app
from server.cli import app
from server.config import get_settings


@app.command()
def serve(
    host: str | None = typer.Option(None, help="Bind address (default SRD_HOST or 127.0.0.1)."),
    port: int | None = typer.Option(None, help="Port (default SRD_PORT or 8000)."),
    log_level: str = typer.Option("info", help="uvicorn log level."),
) -> None:
    """Run the HTTP API; database from SRD_DATABASE_URL (default sqlite:///./srd.db)."""
    settings = get_settings()
    logging.basicConfig(level=log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    uvicorn.run(
        create_app(settings),
        host=host or settings.host,
        port=settings.port if port is None else port,
        log_level=log_level,
        timeout_graceful_shutdown=10,
    )
