"""Connection hygiene of ``srd serve``: what uvicorn's HTTP protocol lacks.

uvicorn closes idle keep-alive connections (``timeout_keep_alive``) and answers 503 past
``limit_concurrency``, but a connection that never finishes sending a request holds its socket
and file descriptor for ever: nothing times out a header or a body still arriving. (h11 caps an
unfinished header's size, ``h11_max_incomplete_event_size``; httptools, which ``srd serve``
uses, does not.) ``timed_protocol`` is uvicorn's httptools protocol plus:

* a header deadline: from the connection's start, or a request's first byte, its whole header
  must arrive within ``header_timeout_s``, else the connection gets 408 and is closed;
* a header this server will not serve gets its answer before any app sees it: an HTTP/1.1
  request without exactly one ``Host`` 400 (RFC 9112, 3.2), a version other than 1.0 and 1.1
  in the request line 505, a method other than GET asking to upgrade 400, a method the
  parser does not know 501;
* a header size cap: a header past ``max_header_bytes`` or ``MAX_HEADER_FIELDS`` lines (a
  chunked body's trailer counts as header) gets 431 and the connection is closed (counted as
  it arrives, and as the parser reads it, so a header that rides in behind another request's
  in one read is counted too);
* a body framing cap: a body's bytes on the wire, chunk sizes and extensions included, at
  most ``max_body_bytes`` and a quarter more (413), and at most ``MAX_CHUNKS`` chunks (400):
  the app bounds and counts a body's payload, which a body of one-byte chunks or of long
  chunk extensions made cheap against what it cost to parse;
* a body deadline: the request's whole body must arrive within ``body_timeout_s`` of its
  header, else the connection gets 408 (if no answer has started) and is closed (the app
  sees the client go away);
* an arrival time: the moment each request's last byte is parsed is put in its scope
  (``RECEIVED_AT``), by which a remote round judges an upload's deadline;
* a share per address: one client address holds at most ``max_per_address`` open connections
  (a trusted proxy's are not counted), and no more than the server has left free once it holds
  an eighth of that (``address_share``); past it a new connection gets 429 and is closed, so a
  few addresses cannot take the connections everyone shares (``limit_concurrency``).

Each of these answers, an unreadable request's 400 and a connection past ``limit_concurrency``
(503), carries the common JSON error body.
A WebSocket upgrade leaves these deadlines, and the connection count, once its handshake header
is in: the socket's own pings and limits (``server.api.limits``) take over, and
``GuardedWebSocketProtocol``, uvicorn's WebSocket protocol plus bounds on what frames cost below
the app (control frames, a message's fragments, frames after the close), which the messages'
own allowance never sees, and whose handshake refusals carry the common JSON body. Requests
pipelined on one connection are answered in order, a refusal after the answers of the
requests before it (a refused request queued behind them never starts).
"""

from __future__ import annotations

import asyncio
import ipaddress
import json
import logging
import resource
import time
from collections import Counter
from collections.abc import Callable
from datetime import UTC, datetime
from email.utils import formatdate
from http import HTTPStatus
from typing import Any, ClassVar

import httptools
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol, RequestResponseCycle
from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
from websockets.datastructures import Headers
from websockets.exceptions import InvalidHeader, InvalidHeaderValue
from websockets.http11 import Response

from server.api.hardening import SECURITY_HEADERS

log = logging.getLogger("srd.connections")

IPV6_CLIENT_PREFIX = 64
"""An IPv6 client is its /64 network: one host usually holds a whole /64, so counting its
single addresses would give it a share per address it cares to use."""


class HeaderRefusedError(Exception):
    """Raised in a parser callback to stop the parser once a header is refused."""


def client_address(host: str) -> str:
    """The client a peer address counts as, everywhere a share or a quota is per address: an
    IPv4 address (an IPv4-mapped IPv6 one too) as it is, an IPv6 address as its /64 network,
    anything else (a Unix socket's name) as it is."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return host
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, IPV6_CLIENT_PREFIX), strict=False))
    return host


FD_RESERVE = 256
"""File descriptors kept free of client connections: the database, logs, worker pipes."""


LINGER_S = 1.0
"""How long a refused connection stays open after its answer, its client's bytes dropped."""
RETRY_AFTER_S = 2
"""``Retry-After`` of a connection refused past its address's share."""
LINGERING_PER_ADDRESS = 4
"""Connections of one address refused as they opened that linger at once (``LINGER_S``);
the others close once answered."""


_SECURITY_LINES = b"".join(
    f"{name.lower()}: {value}\r\n".encode() for name, value in SECURITY_HEADERS.items()
)
"""The security headers every answer carries (``server.api.hardening``), as header lines."""


def _error_body(loc: list[str], msg: str, kind: str) -> bytes:
    """The common error body (``server.api.errors``) of one refusal."""
    item = {"loc": loc, "msg": msg, "type": kind}
    return json.dumps({"detail": [item]}, separators=(",", ":")).encode()


def _answer(status: bytes, msg: str, kind: str, *, headers: bytes = b"") -> bytes:
    """A whole response with the common error body and the security headers, closing."""
    body = _error_body(["connection"], msg, kind)
    return b"".join(
        (
            b"HTTP/1.1 " + status + b"\r\ncontent-type: application/json\r\n",
            b"content-length: %d\r\nconnection: close\r\n" % len(body),
            _SECURITY_LINES,
            headers,
            b"\r\n",
            body,
        )
    )


TIMEOUT_ANSWER = _answer(
    b"408 Request Timeout", "the request's header did not arrive in time", "header_timeout"
)
BODY_TIMEOUT_ANSWER = _answer(
    b"408 Request Timeout", "the request's body did not arrive in time", "body_timeout"
)
TOO_LARGE_ANSWER = _answer(
    b"431 Request Header Fields Too Large", "the request's header is too large", "header_too_large"
)
MAX_HEADER_FIELDS = 100
"""Header lines one request may carry (Apache's ``LimitRequestFields``): 12,000 empty lines,
within the header's byte cap, had cost 20 ms of the event loop a request, before any rate."""
TOO_MANY_FIELDS_ANSWER = _answer(
    b"431 Request Header Fields Too Large",
    f"a request's header (and a chunked body's trailer) has at most {MAX_HEADER_FIELDS} lines",
    "header_too_large",
)
MAX_CHUNKS = 1024
"""Chunks one chunked body may come in (each costs a call into Python)."""
TOO_MANY_CHUNKS_ANSWER = _answer(
    b"400 Bad Request",
    f"a chunked body comes in at most {MAX_CHUNKS} chunks: send larger ones",
    "too_many_chunks",
)
HOST_ANSWER = _answer(
    b"400 Bad Request",
    "a request carries at most one Host header, an HTTP/1.1 request exactly one (RFC 9112, 3.2)",
    "bad_host",
)
VERSION_ANSWER = _answer(
    b"505 HTTP Version Not Supported",
    "this server speaks HTTP/1.0 and HTTP/1.1 on this connection",
    "http_version",
)
METHOD_ANSWER = _answer(
    b"501 Not Implemented",
    "the request's method is not one this server knows (methods are case-sensitive)",
    "unknown_method",
)
CONNECT_ANSWER = _answer(
    b"501 Not Implemented",
    "CONNECT (a tunnel) is not served: this server is no proxy",
    "unknown_method",
)
UPGRADE_ANSWER = _answer(
    b"400 Bad Request",
    "only a GET may ask to upgrade (a WebSocket handshake): send this request without Upgrade",
    "bad_upgrade",
)
UPGRADE_BODY_ANSWER = _answer(
    b"400 Bad Request",
    "a request asking to upgrade carries no body: send it without Upgrade",
    "bad_upgrade",
)
FULL_ANSWER = _answer(
    b"503 Service Unavailable",
    "the server holds as many connections as it can; retry shortly",
    "server_full",
    headers=b"retry-after: %d\r\n" % RETRY_AFTER_S,
)
TOO_MANY_ANSWER = _answer(
    b"429 Too Many Requests",
    "this address holds its share of open connections already; retry when one has closed",
    "too_many_connections",
    headers=b"retry-after: %d\r\n" % RETRY_AFTER_S,
)


def address_share(max_per_address: int, limit: int | None, open_now: int) -> int:
    """How many open connections one address may hold while the server holds ``open_now`` of
    its ``limit``: ``max_per_address``, but once the address holds an eighth of that, no more
    than are left free. Each new heavy address thus gets at most half of what is left: eight
    addresses at the full share would take every connection, this way a few heavy ones leave
    room for everyone else (a server full of many light addresses is full all the same)."""
    if limit is None:
        return max_per_address
    floor = max(1, max_per_address // 8)
    return min(max_per_address, max(floor, limit - open_now))


class _MethodAwareParser:
    """httptools' request parser, remembering whether it failed on an unknown method (RFC 9110,
    9.1: 501) rather than on another unreadable request (400), and reading on past an upgrade
    the server declines (``upgrading()`` False): the parser stops at such a request's end, and
    the requests pipelined behind it had been dropped unanswered."""

    def __init__(self, parser: httptools.HttpRequestParser, upgrading: Callable[[], bool]) -> None:
        self._parser = parser
        self._upgrading = upgrading
        self.unknown_method = False

    def feed_data(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                self._parser.feed_data(view)
                return
            except httptools.HttpParserInvalidMethodError:
                self.unknown_method = True
                raise
            except httptools.HttpParserUpgrade as upgrade:
                if self._upgrading():
                    raise
                view = view[upgrade.args[0] :]  # declined: served as HTTP/1.1 (RFC 9110, 7.8)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._parser, name)


RECEIVED_AT = "srd.received_at"
"""The scope key of the moment a request's last byte was parsed (``srd serve`` only)."""

PIPELINED_BEHIND = "srd.pipelined_behind"
"""The scope key of an ``asyncio.Event`` set once another request is pipelined behind this one
on its connection (``srd serve`` only). A long poll answers then, as if its wait were over:
the requests behind it wait for its answer, and an upload among them, judged at arrival but
stored when its route runs, had been made late by a long wait."""


BODY_SLICE_BYTES = 65_536
"""What the HTTP parser reads at once (``TimedHttpProtocol.data_received``)."""


class TimedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with header and body deadlines (module docstring); the
    limits are class attributes, set by ``timed_protocol``."""

    header_timeout_s = 10.0
    body_timeout_s = 30.0
    send_timeout_s = 30.0
    """An answer the peer reads none of for this long (the transport's buffer full the whole
    time) ends its connection."""
    max_header_bytes = 65_536
    max_body_bytes = 262_144
    max_per_address = 512
    exempt: ClassVar[tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]] = ()
    """Networks whose connections are not counted (the trusted proxies)."""
    open_by_address: ClassVar[Counter[str]] = Counter()
    """Open connections per client address (one counter per configured class)."""
    lingering: ClassVar[Counter[str]] = Counter()
    """Connections refused as they opened and still lingering, per client address."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._method_aware = _MethodAwareParser(self.parser, self._should_upgrade)
        self.parser = self._method_aware  # type: ignore[assignment]
        self._deadline: asyncio.TimerHandle | None = None
        self._reading_header = True
        self._header_bytes = 0
        self._tail = b""  # the last bytes of the header read so far (its end may straddle reads)
        self._counted: str | None = None  # the address this connection is counted against
        self._lingering: str | None = None  # refused as it opened: counted there, lingering
        self._refused = False  # answered with an error: what else arrives is dropped
        self._header_parsed = 0  # the current request's header bytes, as the parser reads them
        self._header_fields = 0  # and its lines (a trailer's too)
        self._body_wire = 0  # the current body's bytes as they arrive, framing included
        self._chunks = 0  # and its chunks
        self._in_body = False  # between a request's header and its end: self.cycle is its own
        self._begun = False  # the parser is in a request (its line has begun)
        self._after_response: bytes | None = None  # a refusal waiting for the answer in flight
        self._stall: asyncio.TimerHandle | None = None  # armed while the peer reads nothing
        self._running: Any = None  # the cycle whose app runs (pipelined ones wait behind it)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        host = self.client[0] if self.client else None
        counted = host is not None and not self._exempt(host)
        address = client_address(host) if host is not None and counted else None
        if self.limit_concurrency is not None and len(self.connections) >= self.limit_concurrency:
            self._refuse_at_open(FULL_ANSWER, address)  # uvicorn's 503 comes later, plain text
            return
        if address is not None:
            held = self.open_by_address[address]
            open_now = len(self.connections) - 1  # before this one
            if held >= address_share(self.max_per_address, self.limit_concurrency, open_now):
                self._refuse_at_open(TOO_MANY_ANSWER, address)
                return
            self.open_by_address[address] += 1
            self._counted = address
        self._arm(self.header_timeout_s, header=True)

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        self._unstall()
        running = self._running
        if running is not None and running is not self.cycle and not running.response_complete:
            # uvicorn tells only the last request parsed (one pipelined behind): the one
            # running is told too, so that an event stream or an answer being sent ends now
            running.disconnected = True
            running.message_event.set()
        self._uncount()
        if self._lingering is not None:
            self.lingering[self._lingering] -= 1
            if self.lingering[self._lingering] <= 0:
                del self.lingering[self._lingering]
            self._lingering = None
        super().connection_lost(exc)

    def _start_asgi_task(self, cycle: Any, app: Any) -> None:
        self._running = cycle
        super()._start_asgi_task(cycle, app)

    def pause_writing(self) -> None:
        super().pause_writing()
        if self._stall is None:
            self._stall = self.loop.call_later(self.send_timeout_s, self._stalled)

    def resume_writing(self) -> None:
        self._unstall()
        super().resume_writing()

    def _unstall(self) -> None:
        if self._stall is not None:
            self._stall.cancel()
            self._stall = None

    def _stalled(self) -> None:
        """The peer read nothing of an answer for ``send_timeout_s``: its connection ends (the
        kernel's buffers and the answer's file and memory held for it are freed)."""
        self._stall = None
        self.transport.abort()

    def data_received(self, data: bytes) -> None:
        # Parsed in slices, so that a body's bytes on the wire are counted (at most one slice
        # after its header's end is not) and a refusal stops the parse between two slices.
        for start in range(0, len(data), BODY_SLICE_BYTES):
            if self.transport.is_closing() or self.transport.get_protocol() is not self:
                return  # ended, or upgraded: a client sends frames only after the 101 (RFC 6455)
            self._received(data[start : start + BODY_SLICE_BYTES])

    def _received(self, data: bytes) -> None:
        if self._refused:
            return  # read and dropped, so that the close sends the answer, not a reset
        if self._reading_header:
            if not self._begun:  # empty lines before a request (RFC 9112, 2.2): header bytes
                self._header_bytes += len(data) - len(data.lstrip(b"\r\n"))
                if self._deadline is None:  # uvicorn's keep-alive timer stopped at them
                    self._arm(self.header_timeout_s, header=True)
            seen = self._tail + data
            end = seen.find(b"\r\n\r\n")  # the header's end, if it is in these bytes
            self._header_bytes += len(data) if end < 0 else max(0, end + 4 - len(self._tail))
            self._tail = seen[-3:]
            if self._header_bytes > self.max_header_bytes:
                self._refuse(TOO_LARGE_ANSWER)
                return
        elif self._in_body:
            self._body_wire += len(data)
            if self._body_wire > self._wire_limit:
                self._refuse(self._too_large_body)
                return
        super().data_received(data)

    def send_400_response(self, msg: str) -> None:
        """An unreadable request (uvicorn's parser said so): 400 with the common body."""
        if self._refused:  # the parser was stopped after a refusal (``_parsed``)
            return
        if self._method_aware.unknown_method:
            self._refuse(METHOD_ANSWER)
        else:  # after the answers of the requests before it, as every refusal
            self._refuse(_answer(b"400 Bad Request", msg, "bad_request"))

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._begun = True
        self._header_parsed = self._header_fields = self._body_wire = self._chunks = 0
        if self._deadline is None or not self._reading_header:
            self._arm(self.header_timeout_s, header=True)

    def on_url(self, url: bytes) -> None:
        self._parsed(len(url))
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._parsed(len(name) + len(value) + 4)  # ": " and the line's end
        self._header_fields += 1
        if self._header_fields > MAX_HEADER_FIELDS:
            self._refuse(TOO_MANY_FIELDS_ANSWER)
            raise HeaderRefusedError
        super().on_header(name, value)

    def on_chunk_header(self) -> None:
        self._chunks += 1
        if self._chunks > MAX_CHUNKS + 1:  # the last chunk, of size 0, ends the body
            self._refuse(TOO_MANY_CHUNKS_ANSWER)
            raise HeaderRefusedError

    def _parsed(self, size: int) -> None:
        """Count a header's parsed bytes, request by request: ``data_received`` counts bytes
        as they arrive, but a read that ends one request's header can carry the whole header
        of the next (pipelined), past its count. Over the cap: 431, and the parser stops."""
        self._header_parsed += size
        if self._header_parsed > self.max_header_bytes:
            self._refuse(TOO_LARGE_ANSWER)
            raise HeaderRefusedError

    def on_headers_complete(self) -> None:
        self._disarm()
        self._reading_header = False
        refusal = self._header_refusal()
        if refusal is not None:
            self._refuse(refusal)
            raise HeaderRefusedError  # the parser stops: no body reaches an app
        running = self._running
        self.scope[PIPELINED_BEHIND] = asyncio.Event()  # type: ignore[literal-required]
        super().on_headers_complete()
        if running is not None and not running.response_complete:  # this request waits
            behind = running.scope.get(PIPELINED_BEHIND)  # behind it: tell it
            if isinstance(behind, asyncio.Event):
                behind.set()
        self._in_body = True
        if not self.transport.is_closing():
            self._arm(self.body_timeout_s, header=False)

    def _header_refusal(self) -> bytes | None:
        """The answer to a whole header this server will not serve, or None."""
        version = self.parser.get_http_version()
        if version not in ("1.0", "1.1"):  # "2.0" in an HTTP/1 request line
            return VERSION_ANSWER
        hosts = sum(1 for name, _ in self.headers if name == b"host")
        if hosts > 1 or (hosts == 0 and version == "1.1"):
            return HOST_ANSWER
        if self.parser.get_method() == b"CONNECT":  # the parser takes it for an upgrade
            return CONNECT_ANSWER
        if self.parser.should_upgrade() and self.parser.get_method() != b"GET":
            # The parser hands what follows such a header to the upgrade, not to the body: a
            # POST carrying one had reached the app without its body, or been refused by the
            # WebSocket library with a plain-text 405 naming GET.
            return UPGRADE_ANSWER
        if self.parser.should_upgrade() and any(
            name in (b"transfer-encoding", b"content-length") and value.strip() != b"0"
            for name, value in self.headers
        ):  # the parser stops at its header's end: its body would be read as another request
            return UPGRADE_BODY_ANSWER
        return None

    def on_message_complete(self) -> None:
        self._in_body = self._begun = False
        self._disarm()
        self._reading_header, self._header_bytes, self._tail = True, 0, b""
        # When the whole request was in: an upload's deadline is judged at this moment, the
        # earliest the process knows of it, not when a busy event loop gets round to its route.
        self.scope[RECEIVED_AT] = datetime.now(UTC)  # type: ignore[literal-required]
        super().on_message_complete()

    def handle_websocket_upgrade(self) -> None:
        self._disarm()
        self._uncount()
        super().handle_websocket_upgrade()

    def _should_upgrade(self) -> bool:
        """Only a GET is a WebSocket handshake (RFC 6455, 4.1); another method asking to
        upgrade is refused in ``on_headers_complete``."""
        return self.scope.get("method") == "GET" and super()._should_upgrade()

    def _unsupported_upgrade_warning(self) -> None:
        """An upgrade declined: answered already (``UPGRADE_ANSWER``), nothing to log."""

    def _exempt(self, address: str) -> bool:
        if not self.exempt:
            return False
        try:
            ip = ipaddress.ip_address(address)
        except ValueError:
            return False
        return any(ip in network for network in self.exempt)

    def _uncount(self) -> None:
        if self._counted is not None:
            self.open_by_address[self._counted] -= 1
            if self.open_by_address[self._counted] <= 0:
                del self.open_by_address[self._counted]
            self._counted = None

    def _arm(self, delay_s: float, *, header: bool) -> None:
        self._disarm()
        self._reading_header = header
        self._deadline = self.loop.call_later(delay_s, self._expired, header)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expired(self, header: bool) -> None:
        self._deadline = None
        # A header still arriving has no app behind it yet: it can be answered.
        if header:
            self._refuse(TIMEOUT_ANSWER)
            return
        if not self._abandon_body(BODY_TIMEOUT_ANSWER):
            self._disarm()
            self.transport.close()

    def _abandon_body(self, answer: bytes) -> bool:
        """If the app still reads this request's body and has not begun its answer: it hears
        the client go (what it sends is dropped), and the connection gets ``answer`` and ends.
        False otherwise (a pipelined request waits behind another's answer, which ``answer``
        would break into)."""
        cycle = self.cycle
        if not self._in_body or cycle is None or cycle.response_started or self.pipeline:
            return False
        self._end_reading(cycle, answer)
        return True

    def _end_reading(self, cycle: RequestResponseCycle, answer: bytes) -> None:
        """The app reading ``cycle``'s body hears the client go (what it sends is dropped), and
        the connection gets ``answer`` and ends."""
        cycle.disconnected = True
        cycle.waiting_for_100_continue = False  # its app's first read must not answer 100
        cycle.message_event.set()
        self._refused = True
        self._answer_and_end(answer)

    @property
    def _wire_limit(self) -> int:
        """A body's bytes on the wire, its chunked framing with it (a slice that ends a body
        may carry the next request: counted with it)."""
        return self.max_body_bytes + max(self.max_body_bytes // 4, BODY_SLICE_BYTES)

    @property
    def _too_large_body(self) -> bytes:
        return _answer(
            b"413 Content Too Large",
            f"a request's body is at most {self.max_body_bytes} bytes, and {self._wire_limit} "
            "on the wire with its chunked framing",
            "body_size",
        )

    def _refuse(self, answer: bytes) -> None:
        """Answer and end the connection: the answer, then the end of what this side sends;
        whatever the client still sends is read and dropped for ``LINGER_S``, then the
        connection closes (closing over unread bytes would reset it, and the client could
        lose the answer)."""
        self._disarm()
        if self.transport.is_closing() or self._refused or self._abandon_body(answer):
            return
        self._refused = True
        cycle = self.cycle
        if self._in_body and cycle is not None:
            if cycle.response_started:  # its app answers without its body (a stream): ended
                self._end_reading(cycle, b"")
                return
            if self.pipeline and self.pipeline[0][0] is cycle:  # queued: it never starts
                self.pipeline.popleft()
                cycle.disconnected = True
        if self.pipeline or (cycle is not None and not cycle.response_complete):
            self._after_response = answer  # the answers of the requests before come first
            return
        self._answer_and_end(answer)

    def _refuse_at_open(self, answer: bytes, address: str | None) -> None:
        """Refuse a connection as it opens: lingering as any refusal (``_refuse``) while its
        address (None: a trusted proxy's) holds fewer than ``LINGERING_PER_ADDRESS`` such
        refusals, else closed once the answer is written: an address opening connections past
        its share as fast as it could had held 3,900 lingering at once, taking the server to
        its connection limit for everyone. A request such a connection sent already may reset
        it and lose the answer."""
        if address is not None and self.lingering[address] >= LINGERING_PER_ADDRESS:
            self._refused = True
            self.transport.write(answer)
            self.transport.close()
            return
        if address is not None:
            self.lingering[address] += 1
            self._lingering = address
        self._refuse(answer)

    def on_response_complete(self) -> None:
        queued = bool(self.pipeline)  # the next request starts now, and answers first
        super().on_response_complete()
        if self._after_response is not None and not queued:
            answer, self._after_response = self._after_response, None
            self._answer_and_end(answer)

    def _answer_and_end(self, answer: bytes) -> None:
        if self.transport.is_closing():
            return
        self.transport.write(answer)
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self._deadline = self.loop.call_later(LINGER_S, self.transport.close)


def timed_protocol(
    *,
    header_timeout_s: float,
    body_timeout_s: float,
    max_header_bytes: int,
    max_per_address: int,
    max_body_bytes: int = TimedHttpProtocol.max_body_bytes,
    send_timeout_s: float = TimedHttpProtocol.send_timeout_s,
    exempt: list[str] | tuple[str, ...] = (),
) -> type[TimedHttpProtocol]:
    """The protocol class of ``srd serve`` with these limits (``exempt``: addresses or
    networks whose connections are not counted per address)."""
    return type(
        "ConfiguredTimedHttpProtocol",
        (TimedHttpProtocol,),
        {
            "header_timeout_s": header_timeout_s,
            "body_timeout_s": body_timeout_s,
            "send_timeout_s": send_timeout_s,
            "max_header_bytes": max_header_bytes,
            "max_per_address": max_per_address,
            "max_body_bytes": max_body_bytes,
            "exempt": tuple(ipaddress.ip_network(entry, strict=False) for entry in exempt),
            "open_by_address": Counter(),
            "lingering": Counter(),
        },
    )


def raise_file_limit() -> int:
    """Raise the soft limit of open files to the hard one; the soft limit now."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 20)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError) as exc:  # some systems cap it below the hard limit
            log.warning("could not raise the open-file limit from %d to %d: %s", soft, target, exc)
    return soft


def connection_cap(wanted: int, file_limit: int) -> int:
    """Connections ``srd serve`` holds at most: ``wanted``, below the file-descriptor limit."""
    return max(16, min(wanted, file_limit - FD_RESERVE))


CLOSE_WAIT_S = 2.0
"""How long a socket closed for its control frames waits for the peer's close before it ends
the connection (closing over unread bytes would reset it, and the peer could lose the close)."""
CONTROL_BURST, CONTROL_PER_S = 64, 16.0
"""Control frames (pings, pongs) one socket may send: a burst, refilled per second, as its
messages' allowance (``server.auctions.sockets``); past it the socket is closed with 1008."""


class TokenBucket:
    """A token bucket: ``take`` is False once the allowance is spent."""

    def __init__(self, burst: int, refill_per_s: float) -> None:
        self._burst, self._refill = float(burst), refill_per_s
        self._tokens, self._at = float(burst), time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self._tokens = min(self._burst, self._tokens + (now - self._at) * self._refill)
        self._at = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True


MAX_FRAGMENTS = 64
"""Frames one message may come in (browsers send one; a client that splits the largest
message a round socket takes into 4 KiB frames sends 34): parsing a frame costs about 5 µs
of the event loop, and a message sent as 130,000 one-byte frames had held it 0.65 s."""
READ_SLICE_BYTES = 16_384
"""What the frame parser reads at once (a socket past its bounds is stopped between slices):
at most about 2,300 of the smallest frames, some 12 ms."""
HANDSHAKE_MSG_CHARS = 160
"""The longest message of a refused handshake: the library's quotes the header's value whole
(a ``Sec-WebSocket-Key`` of 6 KB came back in the answer)."""


class GuardedWebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's WebSocket protocol plus bounds on what the peer's frames cost below the app.
    uvicorn answers a ping at once, so the app's message allowance never counts it: one
    socket's pings (25 MB in 8 s) had held a core, and a peer that did not read its pongs grew
    the server's write buffer by 54 MB a second. Here pings and pongs share a token bucket, a
    message comes in at most ``MAX_FRAGMENTS`` frames, and once the server has sent its close
    the peer's data frames (dropped unread by the app) take the same bucket; past a bound the
    socket is closed with 1008 and what the peer still sends is dropped unparsed. A ping that
    finds the write buffer full pauses reading until it drains."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.conn.reject = self._refused  # type: ignore[method-assign]
        self._control = TokenBucket(CONTROL_BURST, CONTROL_PER_S)
        self._reading_held = False
        self._fragments = 0  # frames of the message being read
        self._dropping = False  # closed for its frames: the rest is not parsed

    def _refused(self, status: int, text: str) -> Response:
        """The answer to a handshake the WebSocket library refuses (no or a bad
        ``Sec-WebSocket-Key`` or ``Sec-WebSocket-Version``, an ``Upgrade`` or ``Connection``
        that asks for no WebSocket): the common JSON error body naming the header, with the
        security headers, instead of the library's plain text; a version this server does not
        speak is 426 with the one it does (RFC 6455, 4.2.2)."""
        refusal = self.conn.handshake_exc
        version = isinstance(refusal, InvalidHeader) and refusal.name == "Sec-WebSocket-Version"
        if version and isinstance(refusal, InvalidHeaderValue):
            status = 426
        loc = ["header", refusal.name] if isinstance(refusal, InvalidHeader) else ["connection"]
        msg = text.strip().removeprefix("Failed to open a WebSocket connection: ").split("\n")[0]
        if len(msg) > HANDSHAKE_MSG_CHARS:  # the header's value it quotes is the peer's
            msg = msg[:HANDSHAKE_MSG_CHARS] + "…"
        body = _error_body(loc, msg.rstrip(".") or "the handshake failed", "handshake")
        headers = Headers(
            [
                ("Date", formatdate(usegmt=True)),
                ("Content-Type", "application/json"),
                ("Content-Length", str(len(body))),
                ("Connection", "close"),
                *SECURITY_HEADERS.items(),
            ]
        )
        if version:
            headers["Sec-WebSocket-Version"] = "13"
            if status == 426:  # the library adds it to its own 426s only
                headers["Upgrade"] = "websocket"
        return Response(status, HTTPStatus(status).phrase, headers, body)

    def data_received(self, data: bytes) -> None:
        if self.handshake_initiated and not self.handshake_complete:
            # Frames before the 101 (a client waits for it: RFC 6455, 4.1) are dropped, however
            # the reads cut them: the HTTP parser dropped those read with the handshake, so the
            # next read begins mid-frame (parsed, it ended the socket before its 101).
            return
        for start in range(0, len(data), READ_SLICE_BYTES):
            if self._dropping or self.transport.is_closing():
                return
            super().data_received(data[start : start + READ_SLICE_BYTES])

    def _shut(self, reason: str) -> None:
        """Close with 1008 for the peer's frames; what it still sends is dropped unparsed, and
        the connection ends after ``CLOSE_WAIT_S`` (closing over unread bytes would reset
        it, and the peer could lose the close)."""
        self._dropping = True
        if not self.handshake_complete:  # the app has not accepted it: no close to send yet
            self.transport.close()
            return
        if self.close_sent:  # its close is sent: the peer's answer to it is waited for
            if self.close_timer is None:
                self.close_timer = self.loop.call_later(CLOSE_WAIT_S, self.transport.close)
            return
        self.conn.send_close(1008, reason)
        self.transport.write(b"".join(self.conn.data_to_send()))
        self.close_sent = True
        self.queue.put_nowait({"type": "websocket.disconnect", "code": 1008, "reason": reason})
        self.close_timer = self.loop.call_later(CLOSE_WAIT_S, self.transport.close)

    def _allowed(self) -> bool:
        """Take a control frame's token; False (and the socket closed) when there is none.
        After the close a control frame is not answered, but it takes its token all the same
        (7 MB of pings after a close had held the event loop 8 s)."""
        if self._dropping:
            return False
        if self._control.take():
            return not self.close_sent
        self._shut(f"more than {CONTROL_BURST} pings and pongs at once")
        return False

    def _data_allowed(self, first: bool) -> bool:
        """Count a data frame (``first``: a message's first); False once it breaks a bound."""
        if self._dropping:
            return False
        if self.close_sent:  # read only for the peer's close: the app never sees this frame
            if not self._control.take():
                self._shut("frames after the close")
            return False
        self._fragments = 1 if first else self._fragments + 1
        if self._fragments > MAX_FRAGMENTS:
            self._shut(f"a message comes in at most {MAX_FRAGMENTS} frames")
            return False
        return True

    def handle_parser_exception(self) -> None:
        """Frames the peer could not have meant (sent before the 101, spanning reads): before
        the app has accepted, there is no close to send; the connection ends, unlogged."""
        if not self.handshake_complete:
            self._dropping = True
            self.transport.close()
            return
        super().handle_parser_exception()

    def handle_text(self, event: Any) -> None:
        if self._data_allowed(first=True):
            super().handle_text(event)

    def handle_bytes(self, event: Any) -> None:
        if self._data_allowed(first=True):
            super().handle_bytes(event)

    def handle_cont(self, event: Any) -> None:
        if self._data_allowed(first=False):
            super().handle_cont(event)

    def handle_ping(self) -> None:
        if not self._allowed():
            return
        super().handle_ping()
        if not self.writable.is_set():  # its pongs pile up unread (again, if the app resumed)
            self._reading_held = True
            self.transport.pause_reading()

    def handle_pong(self, event: Any) -> None:
        if self._allowed():
            super().handle_pong(event)

    def resume_writing(self) -> None:
        super().resume_writing()
        if self._reading_held:
            self._reading_held = False
            if not self.read_paused:  # else the app's next receive resumes it
                self.transport.resume_reading()
