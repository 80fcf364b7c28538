"""When round uploads first arrived, kept so that a retry of the same bytes is judged by its
first arrival: after a database outage refused it (503), and after the server was killed
(``kill -9``) between reading its body and storing it.

An API process remembers in memory the arrivals an outage refused. With a journal folder it also
appends a line for every upload under a real token as soon as its body is read and checked, and
a second one once the upload has its answer (stored, refused, or late). The lines go to the
kernel with one ``write`` each, without ``fsync``: a killed process loses nothing the kernel has
(a machine that loses power may lose the last seconds). A server starting on the same folder
reads the journal of the last ``REMEMBERED_S``, remembers every arrival without its answer, and
tells the caller whether there was one: then the runners claim no step for a grace
(``Database.note_outage``), so the agents' retries come before the step that closes their round.

Nothing here is trusted beyond its own bytes: a retry passes every check as any upload does,
and only the arrival of the same bytes, by the same token, for the same patron and round counts.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from collections import OrderedDict
from datetime import UTC, datetime
from pathlib import Path

log = logging.getLogger("srd.arrivals")

REMEMBERED_ARRIVALS = 10_000
"""Arrivals an API process remembers (the oldest forgotten first: about 4.4 MB)."""
REMEMBERED_S = 600.0
"""How long an arrival is remembered; the journal keeps a file per such window, and the last
two."""
JOURNAL_MAX_BYTES = 64 << 20
"""A journal file past this size is written no more until the next window (about 250,000
uploads: 130 bytes a line, two lines an upload), said once in the log."""

Key = tuple[int, int, int, str]


class Arrivals:
    """The first arrival of each round upload that has no answer yet (see the module
    docstring); ``folder``: where its journal lives (None: in memory only)."""

    def __init__(
        self,
        folder: Path | None = None,
        most: int = REMEMBERED_ARRIVALS,
        keep_s: float = REMEMBERED_S,
    ) -> None:
        self._most = most
        self._keep_s = keep_s
        self._arrived: OrderedDict[Key, datetime] = OrderedDict()
        self._folder = folder
        self._window = -1
        self._fd: int | None = None
        self._full_said = False
        self.unanswered_at_start = 0
        """How many journaled arrivals had no answer when this process started."""
        if folder is not None:
            try:
                folder.mkdir(parents=True, exist_ok=True)
                self.unanswered_at_start = self._load(folder)
            except OSError as exc:  # a read-only data folder: the server serves on, and says it
                log.warning("no arrivals journal in %s: %s", folder, exc)
                self._folder = None

    @staticmethod
    def key(auction_id: int, round_number: int, model_id: int, token: str, digest: str) -> Key:
        """An upload's key: its path, its token (hashed) and its body's digest."""
        hashed = hashlib.sha256(token.encode()).hexdigest()
        return auction_id, round_number, model_id, hashed + digest

    def first(self, key: Key, arrived: datetime) -> datetime:
        """The arrival to judge an upload by: its first, if it came before without an answer."""
        first = self._arrived.get(key)
        if first is None or (arrived - first).total_seconds() > self._keep_s:
            return arrived
        return min(first, arrived)

    def arrived(self, key: Key, arrived: datetime) -> None:
        """An upload's body was read and checked: journal its arrival (before it is stored)."""
        self._journal("a", key, arrived)

    def remember(self, key: Key, arrived: datetime) -> None:
        """An outage refused the upload: remember its arrival in memory too."""
        if key not in self._arrived:
            self._arrived[key] = arrived
            while len(self._arrived) > self._most:
                self._arrived.popitem(last=False)

    def answered(self, key: Key, *, journaled: bool = True) -> None:
        """The upload has its answer: its arrival is no longer needed (``journaled``: its
        arrival went to the journal)."""
        if self._arrived.pop(key, None) is not None or (journaled and self._folder is not None):
            self._journal("d", key, None)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _journal(self, kind: str, key: Key, arrived: datetime | None) -> None:
        if self._folder is None:
            return
        window = int(time.time() // self._keep_s)
        try:
            if window != self._window:
                self._open(window)
            assert self._fd is not None
            if os.fstat(self._fd).st_size > JOURNAL_MAX_BYTES:
                if not self._full_said:
                    log.warning("the arrivals journal is full until the next window")
                    self._full_said = True
                return
            stamp = "-" if arrived is None else arrived.isoformat()
            line = f"{kind} {key[0]} {key[1]} {key[2]} {key[3]} {stamp}\n"
            os.write(self._fd, line.encode())
        except OSError as exc:  # a full disk: the upload goes on, its arrival not kept
            log.warning("an upload's arrival was not journaled: %s", exc)

    def _open(self, window: int) -> None:
        assert self._folder is not None
        self.close()
        path = self._folder / f"{window}.log"
        self._fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        self._window, self._full_said = window, False
        for old in self._folder.glob("*.log"):
            if old.stem.isdigit() and int(old.stem) < window - 1:
                old.unlink(missing_ok=True)

    def _load(self, folder: Path) -> int:
        """Remember the journal's arrivals of the last window or two that have no answer."""
        window = int(time.time() // self._keep_s)
        pending: dict[Key, datetime] = {}
        for path in (folder / f"{window - 1}.log", folder / f"{window}.log"):
            try:
                lines = path.read_text(errors="replace").splitlines()
            except FileNotFoundError:
                continue
            for line in lines:
                parts = line.split(" ")
                if len(parts) != 6 or not all(p.isdigit() for p in parts[1:4]):
                    continue  # a line cut short by the kill
                key = (int(parts[1]), int(parts[2]), int(parts[3]), parts[4])
                if parts[0] == "d":
                    pending.pop(key, None)
                elif parts[0] == "a":
                    try:
                        pending.setdefault(key, datetime.fromisoformat(parts[5]))
                    except ValueError:
                        continue
        now = datetime.now(UTC)
        for key, arrived in pending.items():
            if (now - arrived).total_seconds() <= self._keep_s:
                self.remember(key, arrived)
        return len(self._arrived)
