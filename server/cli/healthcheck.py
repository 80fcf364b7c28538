"""``srd healthcheck``: ask the configured server whether it is ready (exit 0) or not (1; a
setting it cannot use is 1 too: an unhealthy container; 130 interrupted).

The container's HEALTHCHECK: it reads the same settings as ``srd serve`` (``SRD_HOST``,
``SRD_PORT``), so it follows the configured port.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

from server.cli.words import FiniteRange

if TYPE_CHECKING:
    import httpx

HEALTHY, UNHEALTHY = 0, 1
ANY_ADDRESS = ("0.0.0.0", "::", "")
"""Bind addresses that mean 'every interface': the check then asks the loopback."""
NOT_IN_A_HOST = "/?#@\\"
"""Characters that would end a URL's host: ``SRD_HOST=a/b`` would ask host a for path /b."""


def health_url(host: str, port: int) -> httpx.URL | None:
    """``http://HOST:PORT/healthz`` for the host ``srd serve`` binds (an IPv6 address bracketed,
    unless it already is; every interface: the loopback), or None if that is no URL of a host
    (``SRD_HOST=127.0.0.1:8000``, ``SRD_HOST=[::1`` ...)."""
    import httpx

    if host.removeprefix("[").removesuffix("]") in ANY_ADDRESS:
        host = "127.0.0.1"
    if any(c in NOT_IN_A_HOST or c.isspace() or not c.isprintable() for c in host):
        return None
    if ":" in host and not (host.startswith("[") and host.endswith("]")):
        host = f"[{host}]"
    try:
        url = httpx.URL(f"http://{host}:{port}/healthz")
    except httpx.InvalidURL:
        return None
    return url if url.path == "/healthz" and (url.port or 80) == port else None


@click.command("healthcheck")
@click.option(
    "--timeout",
    type=FiniteRange(0.1, 60),
    default=4.0,
    show_default=True,
    help="Seconds to wait for the server: to connect, then for its answer.",
)
def command(timeout: float) -> None:
    """Exit 0 when GET /healthz of the configured server (SRD_HOST, SRD_PORT) answers 200 with
    srd's ready answer (status ok), else
    1 (saying why: an unreachable or unready server, a setting that cannot be used); 2 for a
    bad option; 130 when interrupted (Ctrl-C)."""
    import httpx

    from server.config import SettingsError, get_settings

    try:
        settings = get_settings()
    except SettingsError as exc:
        click.echo(f"srd healthcheck: {exc}", err=True)
        raise SystemExit(UNHEALTHY) from None
    url = health_url(settings.host, settings.port)
    if url is None:
        click.echo(
            f"srd healthcheck: SRD_HOST={settings.host}: not a host name or address", err=True
        )
        raise SystemExit(UNHEALTHY)
    try:
        response = httpx.get(url, timeout=timeout)
    except httpx.HTTPError as exc:
        click.echo(f"{url}: {exc}", err=True)
        raise SystemExit(UNHEALTHY) from exc
    status = response.status_code
    healthy = status == 200 and _says_ok(response)
    said = "" if healthy or status != 200 else ", but no srd readiness answer (no status ok)"
    click.echo(f"{url}: {status}{said}", err=not healthy)
    for problem in _problems(response):
        click.echo(f"  {problem}", err=True)
    raise SystemExit(HEALTHY if healthy else UNHEALTHY)


def _says_ok(response: httpx.Response) -> bool:
    """Whether the answer is an srd server's ready one (a JSON object with status ok), not
    another server's page on the same address."""
    try:
        body = response.json()
    except ValueError:
        return False
    return isinstance(body, dict) and body.get("status") == "ok"


def _problems(response: httpx.Response) -> list[str]:
    """The problems a 503 names (none from anything else, or from a body not as expected)."""
    try:
        body = response.json()
        return [f"{p['check']}: {p['msg']}" for p in body.get("problems", [])]
    except (ValueError, TypeError, KeyError, AttributeError):
        return []
