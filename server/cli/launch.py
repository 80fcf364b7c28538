"""Start ``srd serve`` as a child process (``make demo`` does; so do the tests and benchmarks
that run a real server): pick a free port, wait for ``/healthz``, stop gracefully or kill -9."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import TracebackType

import httpx

HEALTH_POLL_S = 0.2


MAX_PORT = 65535
"""The largest TCP port."""


_PASSWORD = re.compile(r"(//[^/?#@:]*:)[^/?#@]*@")
"""The password of a URL's ``user:password@`` part."""


def server_url(_ctx: object, param: object, value: str) -> str:
    """A ``--server`` option's value: an ``http://`` or ``https://`` URL with a host, if it
    names one a TCP port, and no user or password (else a usage error, exit 2, whose message
    never shows a password), without its trailing slash. srd authenticates with bearer
    tokens, in the ``Authorization`` header a URL's credentials would take."""
    import click

    shown = repr(_PASSWORD.sub(r"\1***@", value))
    try:
        parsed = httpx.URL(value) if "://" in value else None
    except httpx.InvalidURL:
        parsed = None
    if parsed is None or parsed.scheme not in ("http", "https") or not parsed.host:
        raise click.BadParameter(
            f"{shown} is not an http:// or https:// URL of a server, e.g. http://127.0.0.1:8000"
        )
    if parsed.port is not None and not 0 < parsed.port <= MAX_PORT:  # httpx takes any number
        raise click.BadParameter(f"{shown}: {parsed.port} is no TCP port (1 to {MAX_PORT})")
    if parsed.userinfo:
        raise click.BadParameter(
            f"{shown}: a server's URL carries no user or password (srd sends bearer tokens, "
            "in the header the URL's credentials would take)"
        )
    return value.rstrip("/")


def settings_environment(values: dict[str, object]) -> dict[str, str]:
    """Settings as the environment of a server process (``SRD_<NAME>``)."""
    return {f"SRD_{name.upper()}": str(value) for name, value in values.items()}


def free_port() -> int:
    """A TCP port free on the loopback interface right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def srd_command() -> list[str]:
    """How to invoke ``srd``: the console script beside this interpreter, else its entry point."""
    script = Path(sys.executable).with_name("srd")
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "from server.cli import main; main()"]


class ServerProcess:
    """``srd serve`` on ``127.0.0.1:<port>`` with its database and data folder."""

    def __init__(
        self,
        *,
        database_url: str,
        data_dir: Path,
        admin_token: str | None = None,
        port: int | None = None,
        extra_env: dict[str, str] | None = None,
        log_path: Path | None = None,
        cwd: Path | None = None,
    ) -> None:
        self.database_url = database_url
        self.data_dir = data_dir
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = log_path or data_dir / "serve.log"
        self._admin_token = admin_token
        self._extra_env = extra_env or {}
        self._cwd = cwd
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def admin_token(self) -> str:
        """The operator token: the one given, else the file the server generated."""
        if self._admin_token is not None:
            return self._admin_token
        return (self.data_dir / "admin_token").read_text().strip()

    def start(self, timeout_s: float = 120.0) -> None:
        """Launch and wait until ``/healthz`` answers (a second ``start`` of a running server
        is an error: it would leave the first one running unseen)."""
        if self.process is not None and self.process.poll() is None:
            raise RuntimeError(f"srd serve on port {self.port} is already running")
        self.data_dir.mkdir(parents=True, exist_ok=True)
        env = {
            **os.environ,
            "SRD_DATABASE_URL": self.database_url,
            "SRD_DATA_DIR": str(self.data_dir),
            **self._extra_env,
        }
        if self._admin_token is not None:
            env["SRD_ADMIN_TOKEN"] = self._admin_token
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with self.log_path.open("ab") as log:
            self.process = subprocess.Popen(
                [*srd_command(), "serve", "--host", "127.0.0.1", "--port", str(self.port)],
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=self._cwd,
            )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"srd serve exited early; see {self.log_path}")
            try:
                if httpx.get(f"{self.url}/healthz", timeout=1.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(HEALTH_POLL_S)
        self.stop()
        raise TimeoutError(
            f"srd serve did not become healthy in {timeout_s} s; see {self.log_path}"
        )

    def kill(self) -> None:
        """SIGKILL the server (no shutdown code runs): a crash."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait()

    def stop(self, timeout_s: float = 30.0) -> None:
        """SIGTERM and wait (graceful shutdown); SIGKILL if it hangs."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()

    def __enter__(self) -> ServerProcess:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()
