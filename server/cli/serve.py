"""``srd serve``: run the auction house API with uvicorn."""

from __future__ import annotations

import contextlib
import logging
from types import FrameType

import click

UNUSABLE = 2
"""The exit code of a server that cannot start with its settings (its data folder)."""


def _drain(app: object) -> None:
    """Tell the app the server is shutting down (its long polls answer now), once it runs."""
    drain = getattr(getattr(app, "state", None), "drain", None)
    if drain is not None:
        with contextlib.suppress(RuntimeError):  # the event loop is already closed
            drain()


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

    class Server(uvicorn.Server):
        """uvicorn's server; on SIGINT or SIGTERM it also drains the app's long polls, which
        would otherwise hold the graceful shutdown for up to ``timeout_graceful_shutdown``."""

        def handle_exit(self, sig: int, frame: FrameType | None) -> None:
            super().handle_exit(sig, frame)
            _drain(self.config.app)

    from server.api.connections import (
        GuardedWebSocketProtocol,
        connection_cap,
        raise_file_limit,
        timed_protocol,
    )
    from server.api.hardening import RedactQueryFilter, SocketLinesFilter
    from server.api.readiness import make_data_dir
    from server.app import create_app
    from server.auctions.sockets import MAX_FRAME_BYTES
    from server.config import get_settings

    settings = get_settings()
    problem = make_data_dir(settings.data_dir)
    if problem is not None:
        click.echo(f"srd serve: {problem} (SRD_DATA_DIR)", err=True)
        raise SystemExit(UNUSABLE)
    logging.basicConfig(level=log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    file_limit = raise_file_limit()
    config = uvicorn.Config(
        create_app(settings),
        host=host or settings.host,
        port=settings.port if port is None else port,
        log_level=log_level,
        access_log=settings.access_log,
        timeout_graceful_shutdown=10,
        ws=GuardedWebSocketProtocol,  # uvicorn's, with its control frames bounded
        ws_max_size=MAX_FRAME_BYTES,  # the round sockets' frames (an upload's manifest)
        http=timed_protocol(
            header_timeout_s=settings.header_timeout_s,
            body_timeout_s=settings.body_timeout_s,
            max_header_bytes=settings.max_header_bytes,
            max_per_address=settings.max_connections_per_address,
            exempt=settings.trusted_proxy_list,
        ),
        timeout_keep_alive=settings.keep_alive_s,  # type: ignore[arg-type]  # a float works
        limit_concurrency=connection_cap(settings.max_connections, file_limit),
        # X-Forwarded-* only from the proxies named (uvicorn's own default trusts loopback).
        proxy_headers=True,
        forwarded_allow_ips=settings.trusted_proxy_list,
    )
    logging.getLogger("uvicorn.access").addFilter(RedactQueryFilter())  # after uvicorn's set-up
    sockets = SocketLinesFilter(handshakes=not settings.access_log)
    logging.getLogger("uvicorn.error").addFilter(sockets)
    server = Server(config)
    server.run()
    if not server.started:  # the port is taken, or the app failed to start
        raise SystemExit(3)
