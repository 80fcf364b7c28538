"""Doorbells: wake another process of the same deployment at once, instead of polling the
database in a tight loop.

A remote fine-tuning round has two waits. The auction's worker waits for the patrons'
uploads, which the API stores; the API's round watcher waits for the worker to open the next
round. Both used to find out by reading the database every few milliseconds. Now the waiting
side listens on a bell and the writing side rings it after its commit. The waiting side
still reads the database, both when it is rung and at a slow fallback period (``FALLBACK_S``),
so a bell that cannot ring (another host, another platform, a full socket buffer) only delays
the wake-up, never loses it.

A bell is a datagram socket in Linux's abstract socket namespace: no file to create or
clean up, gone when its process dies. Its name is scoped by a hash of the database URL, so
servers on one host that share a database (replicas) ring each other's bells and unrelated
deployments never do. Elsewhere than on Linux, ``listen`` returns None and callers poll.
Ringing is fire-and-forget: one non-blocking ``sendto`` that ignores every error.
"""

from __future__ import annotations

import hashlib
import select
import socket
import sys
import threading

FALLBACK_S = 0.05
"""How often a waiter reads the database even when its bell stays silent."""


def scope(database_url: str) -> str:
    """The bell namespace of a deployment: a short hash of its database URL."""
    return hashlib.sha256(database_url.encode()).hexdigest()[:16]


def round_bell(round_id: int) -> str:
    """The bell of the worker waiting for the answers of fine-tuning round ``round_id``; the
    upload writer (in the screening process) rings it after storing answers of that round."""
    return f"round-{round_id}"


def watch_bell(api_pid: int) -> str:
    """The bell of the round watcher in API process ``api_pid``; that process's auction
    workers ring it after every commit (a round opened or closed, an auction moved on)."""
    return f"watch-{api_pid}"


def _address(scope_name: str, name: str) -> str:
    return f"\0srd-bell-{scope_name}-{name}"


class Bell:
    """A bound bell: ``wait`` returns when it was rung (or at the timeout)."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock

    def fileno(self) -> int:
        return self._sock.fileno()

    def drain(self) -> bool:
        """Take every ring queued so far; True if there was any."""
        rung = False
        while True:
            try:
                self._sock.recv(64)
            except OSError:  # BlockingIOError: nothing more is queued
                return rung
            rung = True

    def wait(self, timeout_s: float) -> bool:
        """Until rung or ``timeout_s``; True if rung (every queued ring is taken)."""
        if self.drain():
            return True
        readable, _, _ = select.select([self._sock], [], [], max(0.0, timeout_s))
        if not readable:
            return False
        self.drain()
        return True

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> Bell:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def listen(scope_name: str, name: str) -> Bell | None:
    """Bind the bell ``name`` of the deployment; None if this platform has no abstract
    sockets or another process holds that bell already (the caller then polls)."""
    if not sys.platform.startswith("linux"):
        return None
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind(_address(scope_name, name))
    except OSError:
        sock.close()
        return None
    sock.setblocking(False)
    return Bell(sock)


_sender: socket.socket | None = None
_sender_lock = threading.Lock()


def ring(scope_name: str, name: str) -> None:
    """Ring the bell ``name`` if anyone listens on it; never blocks, never raises."""
    global _sender
    if not sys.platform.startswith("linux"):
        return
    try:
        with _sender_lock:
            if _sender is None:
                _sender = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                _sender.setblocking(False)
            sender = _sender
        sender.sendto(b"!", _address(scope_name, name))
    except OSError:  # nobody listens, its buffer is full, or the platform refuses: they poll
        pass
