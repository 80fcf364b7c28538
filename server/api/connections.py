"""Connection hygiene of ``srd serve``: what uvicorn's HTTP protocol lacks.

uvicorn closes idle keep-alive connections (``timeout_keep_alive``) and answers 503 past
``limit_concurrency``, but a connection that never finishes sending a request holds its socket
and file descriptor for ever: nothing times out a header or a body still arriving. (h11 caps an
unfinished header's size, ``h11_max_incomplete_event_size``; httptools, which ``srd serve``
uses, does not.) ``timed_protocol`` is uvicorn's httptools protocol plus:

* a header deadline: from the connection's start, or a request's first byte, its whole header
  must arrive within ``header_timeout_s``, else the connection gets 408 and is closed;
* a header size cap: a header past ``max_header_bytes`` gets 431 and the connection is closed;
* a body deadline: the request's whole body must arrive within ``body_timeout_s`` of its
  header, else the connection is closed (the app sees the client go away).

A WebSocket upgrade leaves these deadlines once its handshake header is in: the socket's own
pings and limits take over.
"""

from __future__ import annotations

import asyncio
import logging
import resource
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

log = logging.getLogger("srd.connections")

FD_RESERVE = 256
"""File descriptors kept free of client connections: the database, logs, worker pipes."""


def _answer(status: bytes) -> bytes:
    return b"HTTP/1.1 " + status + b"\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"


TIMEOUT_ANSWER = _answer(b"408 Request Timeout")
TOO_LARGE_ANSWER = _answer(b"431 Request Header Fields Too Large")


class TimedHttpProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with header and body deadlines (module docstring); the
    limits are class attributes, set by ``timed_protocol``."""

    header_timeout_s = 10.0
    body_timeout_s = 30.0
    max_header_bytes = 65_536

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._deadline: asyncio.TimerHandle | None = None
        self._reading_header = True
        self._header_bytes = 0

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm(self.header_timeout_s, header=True)

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._reading_header:
            self._header_bytes += len(data)
        super().data_received(data)
        # Still in the header after these bytes (a body in the same read does not count).
        if self._reading_header and self._header_bytes > self.max_header_bytes:
            self._close(TOO_LARGE_ANSWER)

    def on_message_begin(self) -> None:
        super().on_message_begin()
        if self._deadline is None or not self._reading_header:
            self._arm(self.header_timeout_s, header=True)

    def on_headers_complete(self) -> None:
        self._disarm()
        self._reading_header = False
        super().on_headers_complete()
        if not self.transport.is_closing():
            self._arm(self.body_timeout_s, header=False)

    def on_message_complete(self) -> None:
        self._disarm()
        self._reading_header, self._header_bytes = True, 0
        super().on_message_complete()

    def handle_websocket_upgrade(self) -> None:
        self._disarm()
        super().handle_websocket_upgrade()

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
        self._close(TIMEOUT_ANSWER if header else b"")

    def _close(self, answer: bytes) -> None:
        self._disarm()
        if self.transport.is_closing():
            return
        if answer:
            self.transport.write(answer)
        self.transport.close()


def timed_protocol(
    *, header_timeout_s: float, body_timeout_s: float, max_header_bytes: int
) -> type[TimedHttpProtocol]:
    """The protocol class of ``srd serve`` with these limits."""
    return type(
        "ConfiguredTimedHttpProtocol",
        (TimedHttpProtocol,),
        {
            "header_timeout_s": header_timeout_s,
            "body_timeout_s": body_timeout_s,
            "max_header_bytes": max_header_bytes,
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
