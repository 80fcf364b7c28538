"""Per-client limits on the long-lived and costly requests, in one ASGI middleware.

``ClientLimitsMiddleware`` counts, per client, the requests it holds open of each kind:

* round sockets (``WS /auctions/{id}/rounds/socket``), per address;
* event streams (``GET /auctions/{id}/events``, ``GET /jobs/{id}/events``);
* long polls (``GET /auctions/{id}/rounds/current?wait=S`` with S > 0);
* uploads (``PUT /auctions/{id}/rounds/{round}/models/{id}``, ``POST /submit``, and the
  uploads sent on round sockets: ``hold``, called by the socket's route for each).

Every request and WebSocket handshake, and every message received on a round socket
(``RequestRate.take``, called by the socket for each), counts against its address's request
rate: one allowance per address, whatever carries its requests. A request's body, and the
answer of a request held by none of the kinds above (a read), count one more for every
``RATE_BODY_BYTES`` (an answer's once sent, as a debt: what an answer costs to build grows with
its size, and 100 large reads a second were more than the process's event loop can give one
address; a long poll's answer is built once for all its watchers). A request that finds its
address's allowance spent waits for its turn when that comes within ``RATE_PACE_S`` (a client
polling in a tight loop is slowed to the rate, not refused); later than that it is refused. A
round upload (PUT) takes its turn ahead but is not held: its deadline is judged at its arrival,
and its round closes half a second after the deadline.

A client is the SHA-256 of its bearer token where that token is a participant's or the
operator's, else its address (as ``srd serve`` resolved it: a proxy's ``X-Forwarded-For``
counts only from ``SRD_TRUSTED_PROXIES``). A token is looked up (one indexed read) the first
time this process sees it; a made-up token counts against its address, so inventing tokens buys
no shares. As tokens are free to register, an address's tokens together also hold at most a
quarter of the process's event streams, and as many long polls as a quarter of the waits the
process keeps for non-patrons (128). A request over its client's share is answered 429 with
``Retry-After`` and ``Connection: close`` before any route runs: clients are paced, never
queued (but for the request rate's short wait above). The routes' own process-wide caps stay
behind this as the last line.

The request kind is decided by method and path template alone, so the routes behind may
change freely.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import logging
import math
import re
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import parse_qsl

from sqlalchemy.exc import SQLAlchemyError
from starlette.concurrency import run_in_threadpool
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from starlette.websockets import WebSocket

from server.api.connections import client_address
from server.api.errors import RequestError, api_error, problem_response
from server.config import Settings
from server.live.rounds import MAX_WATCHER_WAITERS
from server.store.crud.models import is_participant_token
from server.store.db import Database, DatabaseUnavailableError

log = logging.getLogger("srd.limits")

CLOSE_TRY_AGAIN_LATER = 1013
"""Close code of a refused socket where the server cannot answer its handshake with 429, and of
a round socket whose message was over its address's request rate."""
STATE_KEY = "client_limits"
"""Where a round socket's scope ``state`` holds the limits its messages count against."""
RATE_BURST_S = 4.0
"""An address's request bucket holds this many seconds of its rate."""
RATE_PACE_S = 1.0
"""An HTTP request or handshake past its address's rate waits up to this long for its turn
(its token taken ahead, so an address holds at most this many seconds of its rate waiting);
a round-socket message, as a round upload by PUT, takes its turn ahead and is not held."""
RATE_BODY_BYTES = 16_384
"""A request's body counts as one more request for every this many bytes (by its
``Content-Length``; a chunked one as the largest body taken), and so does a round-socket
message: reading and checking a body costs the event loop by its size (about 10 ms for 256 KB
of numbers), so an address's rate bounds the bytes it makes the server read too. A whole
answer's body counts the same, once sent (about 2 ms of building per 16 KB of JSON)."""
RATE_ADDRESSES = 100_000
"""Addresses whose request buckets a process keeps; past it, it forgets them all."""
TOKEN_VERDICT_KEY = "srd.token_verdict"
"""The request scope's state key of its bearer token's look-up: (digest, real or None)."""
KNOWN_TOKENS = 100_000
"""Digests of real tokens a process remembers; past it, it forgets them all and looks each
up again. A token rotated away (``POST /participants/{name}/token``) stays remembered as
real until then: it keeps a client's share of the limits, never a right (every request that
needs a token checks it against the database)."""


@dataclass(frozen=True)
class Limit:
    """One kind of limited request: its name, as the 429 says it, and the share of one client
    (``per_token`` for clients known by a bearer token, ``per_address`` for the others)."""

    name: str
    per_token: int
    per_address: int
    address_in_all: int | None = None
    """What one address may hold in all, its participant tokens' included (None: no such
    bound beyond its connections')."""


def _template(path: str) -> re.Pattern[str]:
    """A path template (``/auctions/{id}/events``) as a pattern of its paths."""
    parts = ("[^/]+" if part.startswith("{") else re.escape(part) for part in path.split("/"))
    return re.compile("/".join(parts))


class ClientLimitsMiddleware:
    """Refuses, with 429, the requests of a client past its share (module docstring)."""

    def __init__(self, app: ASGIApp, *, settings: Settings) -> None:
        self.app = app
        self.retry_after_s = settings.limit_retry_after_s
        streams = Limit(
            "event streams",
            settings.limit_client_streams,
            settings.limit_client_streams,
            # A token is free to register (a few hundred a day per address): without this,
            # one address's tokens could hold every stream of the process.
            max(settings.limit_client_streams, settings.max_event_streams // 4),
        )
        polls = Limit(
            "long polls",
            settings.limit_client_long_polls,
            settings.limit_client_long_polls,
            max(settings.limit_client_long_polls, MAX_WATCHER_WAITERS // 4),  # as the streams
        )
        self.uploads = uploads = Limit(
            "uploads", settings.limit_client_uploads, settings.limit_address_uploads
        )
        self.socket_limit = Limit(
            "round sockets", settings.limit_client_sockets, settings.limit_client_sockets
        )
        self.upload_path = _template("/auctions/{auction_id}/rounds/{round}/models/{model_id}")
        self.routes: list[tuple[str, re.Pattern[str], Limit]] = [
            ("GET", _template("/auctions/{auction_id}/events"), streams),
            ("GET", _template("/jobs/{job_id}/events"), streams),
            ("GET", _template("/auctions/{auction_id}/rounds/current"), polls),
            ("PUT", self.upload_path, uploads),
            ("POST", _template("/submit"), uploads),
        ]
        self.socket_path = _template("/auctions/{auction_id}/rounds/socket")
        self.held: Counter[tuple[str, str]] = Counter()
        """Requests held open now, by (kind, client)."""
        self.known: set[str] = set()
        """Digests of the tokens found to be real (``KNOWN_TOKENS`` at most)."""
        self.rate = RequestRate(settings.limit_address_requests_per_s, settings.max_body_bytes)

    def limit_of(self, scope: Scope) -> Limit | None:
        """The limit a request counts against, if any."""
        path: str = scope["path"]
        if scope["type"] == "websocket":
            return self.socket_limit if self.socket_path.fullmatch(path) else None
        method: str = scope["method"]
        for route_method, pattern, limit in self.routes:
            if method == route_method and pattern.fullmatch(path):
                if limit.name == "long polls" and not _waits(scope):
                    return None
                return limit
        return None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        delay_s, wait_s = self.rate.take(scope, pace_s=RATE_PACE_S)
        if wait_s:
            await self._refuse(scope, receive, send, self.rate.refusal(wait_s))
            return
        if delay_s and not self._round_upload(scope):  # an upload's token is taken ahead, but
            # it is not held: its deadline is judged at arrival, and the round closes soon after
            await asyncio.sleep(delay_s)
        limit = self.limit_of(scope)
        if limit is None:
            if scope["type"] != "http":
                await self.app(scope, receive, send)
                return
            metered = _Metered(send)
            try:
                await self.app(scope, receive, metered)
            finally:
                self.rate.charge(scope, metered.sent)
            return
        try:
            release = await self.hold(scope, limit)
        except RequestError as refused:
            await self._refuse(scope, receive, send, refused)
            return
        if limit is self.socket_limit or limit is self.uploads:  # its route asks here too
            scope.setdefault("state", {})[STATE_KEY] = self
        try:
            await self.app(scope, receive, send)
        finally:
            release()

    def _round_upload(self, scope: Scope) -> bool:
        return (
            scope["type"] == "http"
            and scope["method"] == "PUT"
            and self.upload_path.fullmatch(scope["path"]) is not None
        )

    async def hold(self, scope: Scope, limit: Limit) -> Callable[[], None]:
        """Count one more request of ``limit`` held by the scope's client, and how to let go of
        it; a RequestError (429, ``Retry-After``) past the client's share."""
        client, share = await self._client(scope, limit)
        keys = [(limit.name, client)]
        if self.held[keys[0]] >= share:
            who = "token" if client.startswith("token:") else "address"
            raise self._over(limit, share, who)
        if limit.address_in_all is not None:  # the address's own and its tokens' together
            keys.append((limit.name, f"all:{_address(scope)}"))
            if self.held[keys[1]] >= limit.address_in_all:
                who = "address (with its participant tokens)"
                raise self._over(limit, limit.address_in_all, who)
        for key in keys:
            self.held[key] += 1

        def release() -> None:
            for key in keys:
                self.held[key] -= 1
                if not self.held[key]:
                    del self.held[key]

        return release

    def message(self, scope: Scope, size: int) -> RequestError | None:
        """Count a message of ``size`` bytes received on the round socket of ``scope`` against
        its address's request rate, as a round upload by PUT counts: its turn taken ahead, up
        to ``RATE_PACE_S`` of the rate, and never held (its deadline is judged at arrival); the
        refusal if it is past that."""
        _, wait_s = self.rate.take(scope, pace_s=RATE_PACE_S, body_bytes=size)
        return self.rate.refusal(wait_s) if wait_s else None

    def _over(self, limit: Limit, share: int, who: str) -> RequestError:
        return _too_many(
            f"this {who} holds {share} {limit.name} already, its share", self.retry_after_s
        )

    async def _client(self, scope: Scope, limit: Limit) -> tuple[str, int]:
        """Who the request counts against, and that client's share of ``limit`` (round
        sockets: always its address). An upload on a round socket counts against its
        handshake's token without a look-up: a made-up one buys nothing there (a socket has
        one upload at a time, and its address's sockets are counted), a real one shares its
        share with its PUTs."""
        if limit is not self.socket_limit:
            token = _bearer(scope)
            if token is not None:
                digest = hashlib.sha256(token).hexdigest()
                if scope["type"] == "websocket" or await self._looked_at(scope, digest):
                    return f"token:{digest}", limit.per_token
        return f"address:{_address(scope)}", limit.per_address

    async def _looked_at(self, scope: Scope, digest: str) -> bool:
        """``_real``, its answer kept in the request's scope for ``real_token``: True only for
        a token known to be real."""
        real = await self._real(scope, digest)
        scope.setdefault("state", {})[TOKEN_VERDICT_KEY] = (digest, real)
        return real is True

    async def real_token(self, scope: Scope, token: str) -> bool:
        """Whether ``token`` may be a participant's or the operator's: known to be (looked up
        once, then remembered; a PUT upload's was, by its own share's count, and is not looked
        up again), or not known not to be (a database that cannot answer)."""
        digest = hashlib.sha256(token.encode()).hexdigest()
        seen = scope.get("state", {}).get(TOKEN_VERDICT_KEY)
        real = (
            seen[1] if seen is not None and seen[0] == digest else await self._real(scope, digest)
        )
        return real is not False

    async def _real(self, scope: Scope, digest: str) -> bool | None:
        """Whether a token digest is a participant's or the operator's (None: the database
        could not answer)."""
        if digest in self.known:
            return True
        services = getattr(scope["app"].state, "services", None)
        if services is None:
            return False
        if digest != services.admin_token_hash:
            try:
                found = await run_in_threadpool(_looked_up, services.database, digest)
            except (DatabaseUnavailableError, SQLAlchemyError) as exc:
                log.debug("a token could not be looked up: %s", exc)  # the routes say it
                return None
            if not found:
                return False
        if len(self.known) >= KNOWN_TOKENS:
            self.known.clear()
        self.known.add(digest)
        return True

    async def _refuse(
        self, scope: Scope, receive: Receive, send: Send, refused: RequestError
    ) -> None:
        response = problem_response(refused)
        response.headers["Connection"] = "close"
        if scope["type"] == "websocket":
            if "websocket.http.response" in scope.get("extensions", {}):
                await WebSocket(scope, receive, send).send_denial_response(response)
            else:  # a server without denial responses: close before accepting
                await send({"type": "websocket.close", "code": CLOSE_TRY_AGAIN_LATER})
            return
        await response(scope, receive, send)


def client_limits(scope: Scope) -> ClientLimitsMiddleware:
    """The limits a round socket's messages and uploads count against (its handshake's), or
    an upload's."""
    limits = scope["state"][STATE_KEY]
    assert isinstance(limits, ClientLimitsMiddleware)
    return limits


def _too_many(what: str, retry_after_s: int) -> RequestError:
    return api_error(
        429,
        f"{what}; retry in {retry_after_s} s",
        loc=("client",),
        kind="too_many_requests",
        headers={"Retry-After": str(retry_after_s)},
    )


class RequestRate:
    """Requests per address: a token bucket each (``RATE_BURST_S`` of ``per_s`` deep), the
    operator's token not counted."""

    def __init__(self, per_s: float, max_body_bytes: int) -> None:
        self.per_s = per_s
        self.max_body_bytes = max_body_bytes
        self._depth = per_s * RATE_BURST_S
        self._buckets: dict[str, tuple[float, float]] = {}  # address -> (tokens, when)

    def refusal(self, wait_s: int) -> RequestError:
        """The 429 of a request ``take`` refused (``wait_s``: its answer)."""
        return _too_many(
            f"this address sends more than {self.per_s:g} requests a second, its share (a "
            f"body and an answer count one more for every {RATE_BODY_BYTES} bytes)",
            wait_s,
        )

    def take(
        self, scope: Scope, *, pace_s: float, body_bytes: int | None = None
    ) -> tuple[float, int]:
        """(delay, refusal) of a request or a message of ``body_bytes`` (None: the request's
        body, by its headers): (0, 0) it goes on now, its tokens taken; (d, 0) it goes on after
        d ≤ ``pace_s`` seconds, its tokens taken ahead; (0, w) it is refused, nothing taken,
        and it would pass in w whole seconds."""
        address = _address(scope)
        now = time.monotonic()
        tokens, when = self._buckets.get(address, (self._depth, now))
        tokens = min(self._depth, tokens + (now - when) * self.per_s)
        size = self._body_bytes(scope) if body_bytes is None else body_bytes
        cost = min(1 + size / RATE_BODY_BYTES, max(1.0, self._depth))  # a full bucket passes it
        delay_s = max(0.0, (cost - tokens) / self.per_s)
        if delay_s and _is_operator(scope):
            return 0.0, 0
        if delay_s > pace_s:
            self._buckets[address] = (tokens, now)
            return 0.0, max(1, math.ceil(delay_s))
        if len(self._buckets) >= RATE_ADDRESSES and address not in self._buckets:
            self._buckets.clear()
        self._buckets[address] = (tokens - cost, now)
        return delay_s, 0

    def charge(self, scope: Scope, answer_bytes: int) -> None:
        """Take what an answer of ``answer_bytes`` costs beyond its request's token, once sent:
        the bucket may go below empty (at most its depth), so the address's next requests wait
        or are refused until the debt is paid back."""
        extra = answer_bytes / RATE_BODY_BYTES
        address = _address(scope)
        if extra < 0.25 or address not in self._buckets or _is_operator(scope):
            return  # small; cleared meanwhile (too many addresses); the operator: not counted
        now = time.monotonic()
        tokens, when = self._buckets[address]
        tokens = min(self._depth, tokens + (now - when) * self.per_s)
        self._buckets[address] = (max(-self._depth, tokens - extra), now)

    def _body_bytes(self, scope: Scope) -> int:
        """The size of the request's body by its headers (a chunked one: the largest taken;
        a wrong ``Content-Length`` is the body checks' to refuse)."""
        chunked = False
        for name, value in scope["headers"]:
            if name == b"content-length" and value.isdigit():
                return min(int(value), self.max_body_bytes)
            chunked = chunked or name == b"transfer-encoding"
        return self.max_body_bytes if chunked else 0


class _Metered:
    """An HTTP answer's ``send``, counting the bytes of its body."""

    def __init__(self, send: Send) -> None:
        self._send = send
        self.sent = 0

    async def __call__(self, message: Message) -> None:
        if message["type"] == "http.response.body":
            self.sent += len(message.get("body", b""))
        await self._send(message)


def _is_operator(scope: Scope) -> bool:
    token = _bearer(scope)
    services = getattr(scope["app"].state, "services", None)
    return (
        token is not None
        and services is not None
        and hmac.compare_digest(hashlib.sha256(token).hexdigest(), services.admin_token_hash)
    )


def _address(scope: Scope) -> str:
    client = scope.get("client")
    return client_address(str(client[0])) if client else "-"


def _looked_up(database: Database, digest: str) -> bool:
    with database.session(write=False) as session:
        return is_participant_token(session, digest)


def _waits(scope: Scope) -> bool:
    """Whether a round read long-polls: ``wait`` above zero (a malformed one is the route's
    to refuse)."""
    for name, value in parse_qsl(scope["query_string"].decode("latin-1")):
        if name == "wait":
            try:
                return float(value) > 0
            except ValueError:
                return False
    return False


def _bearer(scope: Scope) -> bytes | None:
    value: bytes
    for name, value in scope["headers"]:
        if name == b"authorization":
            scheme, _, credentials = value.partition(b" ")
            credentials = credentials.strip()
            if scheme.lower() == b"bearer" and credentials:
                return credentials
            return None
    return None
