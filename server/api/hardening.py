"""Small protections on every answer: security headers, no tokens in URLs, no secrets in the
access log.

``SecurityHeadersMiddleware`` adds to every response that does not set its own: a
Content-Security-Policy that lets nothing load and nobody frame the answer, ``nosniff``,
``X-Frame-Options: DENY`` and ``Referrer-Policy: no-referrer`` (pages set their own policy,
as strict: ``server.ui.routes``). It refuses a ``token`` or ``access_token`` query parameter
with 400 naming it: tokens travel in the ``Authorization`` header, as URLs are logged and
kept in browser histories; that header or ``Last-Event-ID`` given twice (400: which one
counts would be a guess), or a query parameter given twice (400 too: a route reads the last,
a limit might read the first); a query longer than ``MAX_QUERY_BYTES`` (414: no route takes
one, and reading it cost the event loop 1.5 ms a KB); a write (any method but ``GET``,
``HEAD`` and ``OPTIONS``) that a browser marks as sent by another site's page
(``Sec-Fetch-Site: cross-site`` or ``same-site``; without that header, an ``Origin`` of
another host; 403: another site's page would otherwise make its visitors register
participants and spend their addresses' quotas; the API's own clients and the web view are
neither), or that a page sent to a host name the server does not answer pages at (403: DNS
rebinding; ``_unlisted_host``).
``RedactQueryFilter`` blanks such parameters (and any other whose name says secret) in
uvicorn's access log lines, and cuts a line's path to ``MAX_LOGGED_PATH`` characters.

It also answers ``HEAD`` on every ``GET`` path, as HTTP requires of every server (RFC 9110,
section 9.1): the request goes in as a ``GET`` (the same checks, limits and headers, its
``Content-Length`` included) and the response ends after its headers; FastAPI's routes would
answer 405. A stream (an event stream) ends there too.
"""

from __future__ import annotations

import ipaddress
import logging
import re
from collections import Counter
from urllib.parse import parse_qsl, unquote_plus, urlsplit

from fastapi.responses import JSONResponse
from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from starlette.websockets import WebSocket

from server.api.errors import cut, error_item

API_CONTENT_SECURITY_POLICY = (
    "default-src 'none'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)
"""For JSON answers and files: nothing loads from them, nothing frames them."""
SECURITY_HEADERS = {
    "Content-Security-Policy": API_CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
}
TOKEN_PARAMETERS = ("token", "access_token")
"""Query parameters refused with 400, in any case: a token there would be logged."""
ONCE_HEADERS = {
    b"authorization": "Authorization",
    b"last-event-id": "Last-Event-ID",
    b"content-type": "Content-Type",
}
"""Headers refused with 400 when given twice: which one counts would be a guess."""
SECRET_NAME = re.compile(r"token|secret|passw|key|auth|bearer|session|jwt|cred|^pw$|^pass$", re.I)
"""Query parameters whose value the access log never prints."""
SECRET_VALUE = re.compile(r"(srdp|srda)_", re.I)
"""The service's own tokens (participants' ``srdp_``, the generated operator token's
``srda_``): where one stands anywhere in a query, the access log prints the whole query as
``***``."""


SAFE_METHODS = ("GET", "HEAD", "OPTIONS")
"""Methods that write nothing: another site's page may send them."""
MAX_QUERY_BYTES = 4096
"""Longest query string taken (the longest a route reads is a few hundred bytes)."""
MAX_LOGGED_PATH = 1024
"""Characters of a request's path and query an access log line shows (a 404's path can be as
long as a header: 64 KB a line had let one address write 3 MB of log a second)."""

_QUERY_PAIR = re.compile(r"(?<![^&=?])([^&=?]+)=([^&]*)")
"""A ``name=value`` pair of a query. A name starts only where a run of name characters starts:
tried at every character, a long query without "=" was scanned from each (60 KB: 42 s)."""


class SecurityHeadersMiddleware:
    """Security headers on every answer; 400 for a token in the query (module docstring)."""

    def __init__(self, app: ASGIApp, allowed_hosts: tuple[str, ...] = ()) -> None:
        self.app = app
        self.allowed_hosts = allowed_hosts

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        if scope["type"] == "http" and scope["method"] == "HEAD":
            scope = {**scope, "method": "GET"}  # the server's own scope still says HEAD
            send = _headers_only(send)
        if len(scope["query_string"]) > MAX_QUERY_BYTES:
            message = f"the query is longer than {MAX_QUERY_BYTES} bytes"
            await _refuse(
                scope, receive, _with_headers(send), message, ("query",), "query_size", 414
            )
            return
        # a write, or a round socket (which carries uploads, and takes a share of the address's)
        if scope["type"] == "websocket" or scope["method"] not in SAFE_METHODS:
            foreign = _foreign_page(scope["headers"])
            if foreign is not None:
                message = "a request another site's page sent is refused for what it writes"
                loc = ("header", foreign)
                await _refuse(scope, receive, _with_headers(send), message, loc, "cross_site", 403)
                return
            name = _unlisted_host(scope["headers"], self.allowed_hosts)
            if name is not None:
                message = (
                    f"a page at the host name {cut(name)!r} sent this write, and this server "
                    "takes writes from pages at IP addresses, localhost and the names "
                    "SRD_ALLOWED_HOSTS lists only (another site's name that resolves here would "
                    "otherwise pass as this server's own page): if it is this server's name, add "
                    "it to SRD_ALLOWED_HOSTS"
                )
                loc = ("header", "Host")
                await _refuse(
                    scope, receive, _with_headers(send), message, loc, "host_not_allowed", 403
                )
                return
        pairs = parse_qsl(scope["query_string"].decode("latin-1"), keep_blank_values=True)
        counts = Counter(name for name, _ in pairs)  # linear: 13,500 names had taken 3.8 s
        names = counts.keys()
        if len(names) != len(pairs):  # which one counts would be a guess (``?wait=0&wait=30``)
            twice = next(name for name, given in counts.items() if given > 1)
            message = f"the query parameter {cut(twice)!r} is given more than once: give it once"
            loc = ("query", twice)
            await _refuse(scope, receive, _with_headers(send), message, loc, "duplicate_parameter")
            return
        for name in names:
            if name.lower() in TOKEN_PARAMETERS:  # ``?Token=`` is logged as well
                message = (
                    f"a token in the URL ({name!r}) is refused, as URLs are logged: send it as "
                    "'Authorization: Bearer <token>'"
                )
                loc = ("query", name)
                await _refuse(scope, receive, _with_headers(send), message, loc, "token_in_url")
                return
        for header, shown in ONCE_HEADERS.items():
            given = sum(1 for name, _ in scope["headers"] if name == header)
            if given > 1:
                message = f"the {shown} header is given {given} times: send one"
                loc = ("header", shown)
                await _refuse(scope, receive, _with_headers(send), message, loc, "duplicate_header")
                return
        await self.app(scope, receive, _with_headers(send))


def _headers_only(send: Send) -> Send:
    """A response's headers, then its end: what ``HEAD`` answers (the body is dropped, and
    the server, whose scope says HEAD, sends none of it; once the response is complete, a
    stream hears that its client has gone and stops)."""

    async def sender(message: Message) -> None:
        if message["type"] == "http.response.start":
            await send(message)
            await send({"type": "http.response.body", "body": b"", "more_body": False})

    return sender


def _with_headers(send: Send) -> Send:
    async def sender(message: Message) -> None:
        if message["type"] in ("http.response.start", "websocket.http.response.start"):
            headers = MutableHeaders(scope=message)
            for name, value in SECURITY_HEADERS.items():
                if name not in headers:
                    headers.append(name, value)
        await send(message)

    return sender


async def _refuse(
    scope: Scope,
    receive: Receive,
    send: Send,
    message: str,
    loc: tuple[str, ...],
    kind: str,
    status: int = 400,
) -> None:
    """400 for a request whose credentials are in the wrong place or ambiguous (or
    ``status``)."""
    response = JSONResponse(
        {"detail": [error_item(message, loc=loc, kind=kind)]}, status_code=status
    )
    if scope["type"] == "http":
        await response(scope, receive, send)
    elif "websocket.http.response" in scope.get("extensions", {}):
        await WebSocket(scope, receive, send).send_denial_response(response)
    else:
        await send({"type": "websocket.close", "code": 1008})


def _foreign_page(headers: list[tuple[bytes, bytes]]) -> str | None:
    """The header by which a browser says another page than the server's own sent a request
    (its name), or None: ``Sec-Fetch-Site`` ``cross-site`` or ``same-site`` (a sibling
    subdomain, or another port of this host, is another site's page too); without it (an older
    browser), an ``Origin`` whose host name is not the request's ``Host``'s (or ``null``): the
    port is not compared there, as a proxy may pass ``Host`` without it (nginx's ``$host``).
    Scripts and ``srd`` send neither."""
    given = {name: value.strip().lower() for name, value in headers}
    site = given.get(b"sec-fetch-site")
    if site is not None:
        return "Sec-Fetch-Site" if site in (b"cross-site", b"same-site") else None
    origin = given.get(b"origin")
    if origin is None:
        return None
    try:
        own = urlsplit("//" + given.get(b"host", b"").decode("latin-1")).hostname
        theirs = urlsplit(origin.decode("latin-1")).hostname
    except ValueError:  # not an address at all
        return "Origin"
    return None if theirs is not None and theirs == own else "Origin"


def _unlisted_host(headers: list[tuple[bytes, bytes]], allowed: tuple[str, ...]) -> str | None:
    """The host name a browser's page sent a request to, if it is none this server answers
    pages at (or None): DNS rebinding points another site's name at this server, and that
    site's page is then same-origin with it, ``Sec-Fetch-Site`` and ``Origin`` included.
    Answered: IP addresses (a page there is this server's own), ``localhost`` and its
    subdomains (browsers resolve them to the loopback themselves), and ``allowed`` (``*``:
    any; ``*.example.com``: every name under it). A request no page sent (no ``Origin``, no
    ``Sec-Fetch-Site``, or ``Sec-Fetch-Site: none``: a typed address) is not concerned."""
    given = {name: value.strip().lower() for name, value in headers}
    site = given.get(b"sec-fetch-site")
    if site == b"none" or (site is None and b"origin" not in given) or "*" in allowed:
        return None
    host = given.get(b"host", b"").decode("latin-1")
    try:
        name = (urlsplit("//" + host).hostname or "").rstrip(".")
    except ValueError:  # not an address at all
        return host
    if not name:
        return None
    try:
        ipaddress.ip_address(name)
        return None
    except ValueError:
        pass
    if name == "localhost" or name.endswith(".localhost"):
        return None
    for entry in allowed:
        entry = entry.rstrip(".")
        if name == entry or (entry.startswith("*.") and name.endswith(entry[1:])):
            return None
    return name


def redact_query(path: str, secrets: tuple[str, ...] = ()) -> str:
    """``path`` with the values of its secret-named query parameters replaced by ``***``, and
    the whole query if one of the service's tokens (or of ``secrets``: an operator token
    chosen without the ``srda_`` prefix) is still in it anywhere (``?q=Bearer srdp_...``,
    ``?srdp_...``, ``?a=1;t=srdp_...``), and any segment of the path itself that holds one
    (``/nosuch/srdp_...``)."""

    def secret_in(text: str) -> bool:
        plain = unquote_plus(text)
        return SECRET_VALUE.search(plain) is not None or any(each in plain for each in secrets)

    base, mark, query = path.partition("?")
    # a token put in the path (a mistyped address, a probe): that segment goes
    base = "/".join("***" if secret_in(part) else part for part in base.split("/"))
    if not mark:
        return base

    def blank(match: re.Match[str]) -> str:
        name = match.group(1)
        secret = SECRET_NAME.search(unquote_plus(name))  # ``%74oken`` is ``token``
        return f"{name}=***" if secret else match.group(0)

    query = _QUERY_PAIR.sub(blank, query)
    if secret_in(query):
        query = "***"
    return base + mark + query


class RedactQueryFilter(logging.Filter):
    """Blanks secret query parameters in uvicorn's access log records, whose arguments are
    (client, method, path with query, HTTP version, status). ``secrets``: values blanked
    besides the service's own tokens (the operator token, when chosen without its prefix)."""

    def __init__(self, secrets: tuple[str, ...] = ()) -> None:
        super().__init__()
        self.secrets = secrets

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if isinstance(args, tuple) and len(args) >= 3 and isinstance(args[2], str):
            path = redact_query(args[2], self.secrets)
            if len(path) > MAX_LOGGED_PATH:
                path = path[: MAX_LOGGED_PATH - 1] + "…"
            record.args = (*args[:2], path, *args[3:])
        return True


class SocketLinesFilter(logging.Filter):
    """Per-socket lines of ``uvicorn.error``. Always dropped: the WebSocket protocol's own
    ("connection open", "connection closed", "connection rejected (…)", "HTTP response sent
    (…)"), which repeat uvicorn's handshake line. With ``handshakes``, that line too
    (``"WebSocket /path" [accepted]``, or its refusal's status): with the access log off a
    socket is a request like any other, and an auction's agents reconnecting would fill the
    log. A handshake line kept has its secret query parameters blanked, as the access log's
    (its arguments are client, path with query). A text frame that is not UTF-8 (closed with
    1007) is one warning line, without uvicorn's traceback."""

    PROTOCOL = ("connection open", "connection closed", "connection rejected", "HTTP response sent")
    BAD_TEXT = "Invalid UTF-8 sequence received from client"

    def __init__(self, *, handshakes: bool, secrets: tuple[str, ...] = ()) -> None:
        super().__init__()
        self.handshakes = handshakes
        self.secrets = secrets

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.msg
        if not isinstance(message, str):
            return True
        if message.startswith(self.PROTOCOL):
            return False
        if message.startswith(self.BAD_TEXT):  # the client's fault, answered with 1007:
            # one line, not an error with a traceback anyone may write into the log
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            record.exc_info = record.exc_text = None
            return True
        if not message.startswith('%s - "WebSocket %s"'):
            return True
        args = record.args
        if isinstance(args, tuple) and len(args) >= 2 and isinstance(args[1], str):
            record.args = (args[0], redact_query(args[1], self.secrets), *args[2:])
        return not self.handshakes
