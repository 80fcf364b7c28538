"""JSON over HTTP to the auction house: every request retried with exponential backoff on
connection errors, 429 and 503 (honouring Retry-After) until ``give_up_s`` has passed, then
``ServerGoneError`` names the server; bytes of request and response bodies counted, as the
server counts them."""

from __future__ import annotations

import asyncio
import math
import random
import time
from dataclasses import dataclass
from typing import Any

import httpx

HTTP_TIMEOUT_S = 20.0
"""Time allowed for one HTTP exchange (a long poll gets ROUND_WAIT_S more)."""
GIVE_UP_S = 60.0
"""A request that keeps failing is given up after this long."""
RETRY_FIRST_S, RETRY_MAX_S = 0.05, 2.0
"""Backoff between retries: doubling from the first delay up to the largest, with jitter."""
RETRY_STATUSES = frozenset({429, 503})
ONE_CONNECTION = httpx.Limits(max_connections=1, max_keepalive_connections=1)
"""An agent's requests follow one another: one keep-alive connection each."""


class RemoteError(RuntimeError):
    """The server answered something the agent cannot go on with."""


class ServerGoneError(RemoteError):
    """The server did not answer within ``give_up_s`` (its URL is in the message)."""


@dataclass
class Traffic:
    """Bodies sent and received, in bytes, and how many requests (and retries) it took."""

    bytes_up: int = 0
    bytes_down: int = 0
    requests: int = 0
    retries: int = 0


class Backoff:
    """The retry schedule of one request: exponential delays with jitter (``RETRY_FIRST_S``
    doubling to ``RETRY_MAX_S``) until the deadline ``give_up_at`` (monotonic clock); each
    pause counts a retry in ``traffic``."""

    def __init__(self, give_up_at: float, rng: random.Random, traffic: Traffic) -> None:
        self.give_up_at = give_up_at
        self.delay = RETRY_FIRST_S
        self._rng, self._traffic = rng, traffic

    def exhausted(self, at_least_s: float = 0.0) -> bool:
        """The next pause would end past the deadline: the current delay, or ``at_least_s``
        (a server's Retry-After) if longer, even at its shortest jitter."""
        return time.monotonic() + max(self.delay, 0.5 * at_least_s) > self.give_up_at

    async def pause(self, at_least_s: float = 0.0) -> None:
        """Sleep the current delay (or ``at_least_s``, a server's Retry-After, if longer),
        jittered and never past the deadline, then double the delay."""
        self._traffic.retries += 1
        wait = max(self.delay, at_least_s) * (0.5 + self._rng.random())
        await asyncio.sleep(max(min(wait, self.give_up_at - time.monotonic()), 0.0))
        self.delay = min(self.delay * 2, RETRY_MAX_S)


class Client:
    """JSON over HTTP with retries and byte counting (into ``traffic``, which several clients
    may share). Give each agent its own client (one connection, as on its own machine): one
    httpx pool serving many agents' concurrent requests costs time quadratic in their number."""

    def __init__(
        self,
        http: httpx.AsyncClient,
        *,
        give_up_s: float = GIVE_UP_S,
        rng: random.Random | None = None,
        traffic: Traffic | None = None,
    ) -> None:
        self.http = http
        self.give_up_s = give_up_s
        self.traffic = traffic or Traffic()
        self._rng = rng or random.Random(0)

    @property
    def server(self) -> str:
        return str(self.http.base_url)

    async def request(
        self,
        method: str,
        path: str,
        *,
        body: bytes | None = None,
        token: str | None = None,
        timeout_s: float = HTTP_TIMEOUT_S,
        resend: bool = True,
    ) -> httpx.Response:
        """One request, retried on connection errors, 429 and 503 until ``give_up_s``. With
        ``resend=False`` a request that may have reached the server is not sent again (only
        connection failures before sending, 429 and 503 are retried)."""
        headers = {"Content-Type": "application/json"} if body is not None else {}
        if token is not None:
            headers["Authorization"] = f"Bearer {token}"
        backoff = Backoff(time.monotonic() + self.give_up_s, self._rng, self.traffic)
        while True:
            self.traffic.requests += 1
            try:
                response = await self.http.request(
                    method, path, content=body, headers=headers, timeout=timeout_s
                )
            except httpx.TransportError as exc:
                unsent = isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout)
                if not (resend or unsent) or backoff.exhausted():
                    raise ServerGoneError(
                        f"the server at {self.server} did not answer {method} {path} "
                        f"({type(exc).__name__}: {exc}); gave up after {self.give_up_s:.0f} s"
                    ) from exc
                await backoff.pause()
                continue
            self.traffic.bytes_up += len(body or b"")
            self.traffic.bytes_down += len(response.content)
            if response.status_code not in RETRY_STATUSES:
                return response
            wait = retry_after_s(response.headers.get("Retry-After"))
            if backoff.exhausted(wait):
                asked = f" (its Retry-After: {wait:g} s)" if wait else ""
                raise ServerGoneError(
                    f"the server at {self.server} kept answering {response.status_code} "
                    f"to {method} {path}{asked}; gave up after {self.give_up_s:.0f} s"
                )
            await backoff.pause(wait)

    async def json(self, method: str, path: str, **kwargs: Any) -> Any:
        """``request`` that expects a 2xx JSON answer (else RemoteError with the server's)."""
        response = await self.request(method, path, **kwargs)
        if not response.is_success:
            raise RemoteError(f"{method} {path}: {response.status_code} {_error_text(response)}")
        return response.json()


def _error_text(response: httpx.Response) -> str:
    """An error answer's text: this service's JSON error as it is, anything else named as an
    answer no srd server gives (by its media type)."""
    try:
        body = response.json()
    except ValueError:
        body = None
    if isinstance(body, dict) and isinstance(body.get("detail"), list):
        return response.text[:500]
    kind = response.headers.get("content-type", "no media type")[:80]
    return f"an answer of type {kind} that is not an srd server's error (is it an srd server?)"


def retry_after_s(header: str | None) -> float:
    """Seconds of a Retry-After header given in seconds (0 when absent, not a number or not
    finite)."""
    try:
        seconds = float(header or "")
    except ValueError:
        return 0.0
    return seconds if math.isfinite(seconds) and seconds > 0 else 0.0
