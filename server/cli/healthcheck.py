"""``srd healthcheck``: ask the configured server whether it is ready (exit 0) or not (1).

The container's HEALTHCHECK: it reads the same settings as ``srd serve`` (``SRD_HOST``,
``SRD_PORT``), so it follows the configured port.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

if TYPE_CHECKING:
    import httpx

HEALTHY, UNHEALTHY = 0, 1
ANY_ADDRESS = ("0.0.0.0", "::", "")
"""Bind addresses that mean 'every interface': the check then asks the loopback."""


@click.command("healthcheck")
@click.option("--timeout", type=click.FloatRange(0.1, 60), default=4.0, show_default=True)
def command(timeout: float) -> None:
    """Exit 0 when GET /healthz of the configured server answers 200, else 1 (saying why)."""
    import httpx

    from server.config import SettingsError, get_settings

    try:
        settings = get_settings()
    except SettingsError as exc:
        click.echo(f"srd healthcheck: {exc}", err=True)
        raise SystemExit(UNHEALTHY) from None
    host = "127.0.0.1" if settings.host in ANY_ADDRESS else settings.host
    if ":" in host:
        host = f"[{host}]"
    url = f"http://{host}:{settings.port}/healthz"
    try:
        response = httpx.get(url, timeout=timeout)
    except httpx.HTTPError as exc:
        click.echo(f"{url}: {exc}", err=True)
        raise SystemExit(UNHEALTHY) from exc
    status = response.status_code
    click.echo(f"{url}: {status}", err=status != 200)
    for problem in _problems(response):
        click.echo(f"  {problem}", err=True)
    raise SystemExit(HEALTHY if status == 200 else UNHEALTHY)


def _problems(response: httpx.Response) -> list[str]:
    """The problems a 503 names (none from anything else, or from a body not as expected)."""
    try:
        body = response.json()
        return [f"{p['check']}: {p['msg']}" for p in body.get("problems", [])]
    except (ValueError, TypeError, KeyError, AttributeError):
        return []
