"""``srd serve``: run the auction house API with uvicorn."""

from __future__ import annotations

import contextlib
import gc
import logging
import socket
from types import FrameType
from typing import TYPE_CHECKING

import click

from server.cli.words import IntegerRange

if TYPE_CHECKING:
    from server.config import Settings

UNUSABLE = 2
"""The exit code of a server that cannot start with its settings (a variable's value)."""
NOT_STARTED = 3
"""The exit code of a server that could not start: its database, its Ray cluster or its port."""
LOGGED_SECRET_MIN = 8
"""An operator token this long or longer, chosen without the ``srda_`` prefix, is blanked in
the access log wherever it stands in a path or query."""
YOUNG_COLLECTION_EVERY = 20_000
"""The API's cyclic garbage collector looks at its youngest objects after this many container
allocations (Python's default is 700), at each older generation after 20 passes over the one
below: a request allocates thousands of short-lived objects that reference counting frees, so
frequent young collections mostly rescan live ones (docs/performance.md, *Tried on the way*)."""


def admin_token_problem(settings: Settings) -> str | None:
    """Why the operator token file cannot be used, in one line, or None (no file yet: it is
    made at the start; ``SRD_ADMIN_TOKEN`` set: the file is not read)."""
    from server.config import token_problem

    path = settings.admin_token_file
    if settings.admin_token is not None or not path.exists():
        return None
    try:
        token = path.read_text().strip()
    except OSError as exc:
        return f"the admin token file {path} cannot be read: {exc.strerror} (SRD_DATA_DIR)"
    if not token:
        return f"the admin token file {path} is empty: remove it to have one made, or write one"
    problem = token_problem(token)
    if problem is not None:
        return f"the admin token file {path}: {problem}"
    return None


def database_problem(settings: Settings) -> tuple[str, int] | None:
    """Why the server cannot start on its database, in one line naming SRD_DATABASE_URL (its
    password hidden), with the exit code (``UNUSABLE``: the URL itself; ``NOT_STARTED``: the
    database it names), or None. It takes and lets go of a SQLite database's one-server lock and
    migrates the database, as the start does again (quickly, then)."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    from server.store.db import SqliteServerLock, first_line, is_sqlite, prepare_database

    try:
        url = make_url(settings.database_url)
    except ArgumentError:
        return (
            "SRD_DATABASE_URL is not a database URL (sqlite:///... or postgresql+psycopg://...)",
            UNUSABLE,
        )
    if url.get_backend_name() not in ("sqlite", "postgresql"):
        return (
            f"SRD_DATABASE_URL names {url.get_backend_name()}: use sqlite or postgresql",
            UNUSABLE,
        )
    shown = url.render_as_string(hide_password=True)
    try:
        lock = SqliteServerLock(settings.database_url) if is_sqlite(settings.database_url) else None
        try:
            prepare_database(settings.database_url, settings.databases_file)
        finally:
            if lock is not None:
                lock.release()
    except Exception as exc:  # unreachable, refused, read-only, newer schema, another server
        return (
            f"the database {shown} (SRD_DATABASE_URL) cannot be used: {first_line(exc)}",
            NOT_STARTED,
        )
    return None


def port_problem(host: str, port: int) -> str | None:
    """Why ``srd serve`` could not listen on ``host:port`` (taken, or not an address of this
    host), or None: bound as asyncio's ``create_server`` binds it for uvicorn (every address
    the host resolves to, an IPv6 one for IPv6 only), then let go, before anything is made or
    stored (a port taken meanwhile still stops uvicorn, in its own words)."""
    where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"

    def problem(why: str) -> str:
        return f"cannot listen on {where} (--host/--port, SRD_HOST/SRD_PORT): {why}"

    try:
        found = socket.getaddrinfo(
            host, port, socket.AF_UNSPEC, socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
    except (OSError, OverflowError, UnicodeError) as exc:
        return problem(exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc))
    bound: list[socket.socket] = []  # held together, as the server would hold them
    try:
        for family, kind, proto, _, address in dict.fromkeys(
            (f, k, p, "", a) for f, k, p, _, a in found
        ):
            sock = socket.socket(family, kind, proto)
            bound.append(sock)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            try:
                sock.bind(address)
            except OSError as exc:
                return problem(exc.strerror or str(exc))
    finally:
        for sock in bound:
            sock.close()
    return None


def ray_problem(settings: Settings) -> str | None:
    """Why the server cannot start on its Ray cluster (``SRD_JOB_BACKEND=ray``), in one line
    naming SRD_RAY_ADDRESS and the address, or None: a head that takes no TCP connection, or
    an address that answers but where no Ray cluster is joined, within SRD_RAY_JOIN_TIMEOUT_S
    (a head that refuses the connection: at once). The look is the app's own (a child process
    joins and leaves), so a cluster it finds here the app's start finds too."""
    if settings.job_backend != "ray" or settings.ray_address is None:
        return None
    from server.jobs.ray_backend import RayUnavailableError, probe_cpus

    try:
        probe_cpus(settings.ray_address, settings.ray_join_timeout_s)
    except RayUnavailableError as exc:
        return str(exc)
    return None


def _host(_ctx: click.Context, _param: click.Parameter, value: str | None) -> str | None:
    """``--host``: an address to bind, not an empty word (which would bind the default)."""
    from server.config import host_problem

    problem = None if value is None else host_problem(value)
    if problem is not None:
        raise click.BadParameter(problem)
    return value


def _drain(app: object) -> None:
    """Tell the app the server is shutting down (its long polls answer now), once it runs."""
    drain = getattr(getattr(app, "state", None), "drain", None)
    if drain is not None:
        with contextlib.suppress(RuntimeError):  # the event loop is already closed
            drain()


@click.command("serve")
@click.option(
    "--host",
    default=None,
    callback=_host,
    help="Bind address [default: SRD_HOST or 127.0.0.1].",
)
@click.option(
    "--port", type=IntegerRange(0, 65535), default=None, help="Port [default: SRD_PORT or 8000]."
)
@click.option(
    "--log-level",
    type=click.Choice(["critical", "error", "warning", "info", "debug"]),
    default="info",
    show_default=True,
    help="uvicorn log level.",
)
def command(host: str | None, port: int | None, log_level: str) -> None:
    """Run the HTTP API; database from SRD_DATABASE_URL (default sqlite:///./srd.db). Exits,
    saying why in one line, with code 2 for a setting it cannot use (the data folder,
    SRD_DATA_DIR, that cannot be written among them) and 3 when the database cannot be used or
    the address cannot be bound."""
    from server.config import SettingsError, get_settings

    try:  # before the app's imports: a setting it cannot use is said at once
        settings = get_settings()
    except SettingsError as exc:
        for line in str(exc).splitlines():
            click.echo(f"srd serve: {line}", err=True)
        raise SystemExit(UNUSABLE) from None

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
    from server.api.readiness import data_dir_unusable, make_data_dir, unmake_data_dir
    from server.app import create_app
    from server.auctions.sockets import MAX_FRAME_BYTES
    from server.work.pool import LOG_FORMAT

    problem = data_dir_unusable(settings.data_dir)  # made once every check has passed
    if problem is not None:
        click.echo(f"srd serve: {problem} (SRD_DATA_DIR)", err=True)
        raise SystemExit(UNUSABLE)
    problem = admin_token_problem(settings)
    if problem is not None:
        click.echo(f"srd serve: {problem}", err=True)
        raise SystemExit(UNUSABLE)
    bind_host = settings.host if host is None else host
    bind_port = settings.port if port is None else port
    problem = port_problem(bind_host, bind_port)  # before the database: nothing made in vain
    if problem is not None:
        click.echo(f"srd serve: {problem}", err=True)
        raise SystemExit(NOT_STARTED)
    problem = ray_problem(settings)  # before the database: a refused start stores nothing
    if problem is not None:
        click.echo(f"srd serve: {problem}", err=True)
        raise SystemExit(NOT_STARTED)
    problem, made = make_data_dir(settings.data_dir)  # a SQLite database may live in it
    if problem is not None:
        unmake_data_dir(made)  # a refused start leaves nothing behind
        click.echo(f"srd serve: {problem} (SRD_DATA_DIR)", err=True)
        raise SystemExit(UNUSABLE)
    # Logging before the database is readied: its migration, if any, is logged (in one line of
    # ours, ``srd.db``; Alembic's own lines, a revision's whole docstring each, are not).
    logging.basicConfig(level=log_level.upper(), format=LOG_FORMAT)
    logging.getLogger("alembic").setLevel(max(logging.WARNING, logging.getLogger().level))
    refused = database_problem(settings)
    if refused is not None:
        unmake_data_dir(made)
        click.echo(f"srd serve: {refused[0]}", err=True)
        raise SystemExit(refused[1])
    file_limit = raise_file_limit()
    config = uvicorn.Config(
        create_app(settings),
        host=bind_host,
        port=bind_port,
        log_level=log_level,
        access_log=settings.access_log,
        timeout_graceful_shutdown=10,
        ws=GuardedWebSocketProtocol,  # uvicorn's, with its control frames bounded
        ws_max_size=MAX_FRAME_BYTES,  # the round sockets' frames (an upload's manifest)
        http=timed_protocol(
            header_timeout_s=settings.header_timeout_s,
            body_timeout_s=settings.body_timeout_s,
            send_timeout_s=settings.send_timeout_s,
            max_header_bytes=settings.max_header_bytes,
            max_per_address=settings.max_connections_per_address,
            max_body_bytes=settings.max_body_bytes,
            exempt=settings.trusted_proxy_list,
        ),
        timeout_keep_alive=settings.keep_alive_s,  # type: ignore[arg-type]  # a float works
        limit_concurrency=connection_cap(settings.max_connections, file_limit),
        # X-Forwarded-* only from the proxies named (uvicorn's own default trusts loopback).
        proxy_headers=True,
        forwarded_allow_ips=settings.trusted_proxy_list,
    )
    # the operator's token, when chosen without the prefix the filters know (long enough that
    # blanking it cannot blank ordinary words)
    chosen = settings.admin_token.get_secret_value() if settings.admin_token else ""
    secrets = (chosen,) if len(chosen) >= LOGGED_SECRET_MIN else ()
    logging.getLogger("uvicorn.access").addFilter(RedactQueryFilter(secrets))  # after uvicorn's
    sockets = SocketLinesFilter(handshakes=not settings.access_log, secrets=secrets)
    logging.getLogger("uvicorn.error").addFilter(sockets)
    gc.collect()
    gc.freeze()  # what start-up built stays for the process's life: no collection rescans it
    gc.set_threshold(YOUNG_COLLECTION_EVERY, 20, 20)
    server = Server(config)
    server.run()
    if not server.started:  # the port is taken, or the app failed to start
        click.echo(
            f"srd serve: not started on {config.host}:{config.port} (--host/--port, SRD_HOST/"
            "SRD_PORT); the log above says why",
            err=True,
        )
        raise SystemExit(NOT_STARTED)
