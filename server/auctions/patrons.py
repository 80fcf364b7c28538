"""Whose round requests are a patron's: the round sockets and long polls of an auction keep a
share for the participants whose models bid in it, so that others (watchers, or many addresses
each within its own share) cannot take every slot from them (``server.auctions.sockets``,
``server.live.rounds``). A request takes everyone's share while it has room; only when that is
full is its token looked up, for a patron to take the patrons' own."""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable

from sqlalchemy.exc import SQLAlchemyError
from starlette.concurrency import run_in_threadpool

from server.api.security import hash_token
from server.store import crud
from server.store.db import Database, DatabaseUnavailableError

log = logging.getLogger("srd.patrons")

MAX_AUCTIONS = 512
"""Auctions whose patrons' tokens a process remembers, twice the live auctions' default cap
(forgotten all at once past it: at most 512 × an auction's patrons' hashes in memory)."""
MAX_PER_PATRON = 2
"""The patrons' slots (sockets and waits) one participant's token may hold in one auction: its
one patron's request, and one more while it reconnects."""
REREAD_S = 1.0
"""A token not among an auction's patrons read this long ago has them read again (an
enrolling auction takes patrons until it starts)."""


class PatronCheck:
    """Whether a bearer token is a participant's with a patron in an auction: the token hashes
    of an auction's patrons are read in one query and remembered, read again for a token they
    do not hold once they are ``REREAD_S`` old."""

    def __init__(self, database: Database) -> None:
        self._database = database
        self._tokens: dict[int, tuple[float, frozenset[str]]] = {}
        self._held: Counter[tuple[int, str]] = Counter()

    async def claim(self, auction_id: int, token: str | None) -> Callable[[], None] | None:
        """A hold on one of the patrons' slots of the auction for this token, and how to let
        go of it; None if the token is no patron's there, or holds ``MAX_PER_PATRON``
        already (one patron of one auction cannot take the share of every other's)."""
        if not await self.is_patron(auction_id, token):
            return None
        assert token is not None
        key = (auction_id, hash_token(token))
        if self._held[key] >= MAX_PER_PATRON:
            return None
        self._held[key] += 1

        def release() -> None:
            self._held[key] -= 1
            if not self._held[key]:
                del self._held[key]

        return release

    async def is_patron(self, auction_id: int, token: str | None) -> bool:
        if not token:
            return False
        digest = hash_token(token)
        read_at, tokens = self._tokens.get(auction_id, (-REREAD_S, frozenset()))
        if digest in tokens:
            return True
        if time.monotonic() - read_at < REREAD_S:
            return False
        try:
            tokens = await run_in_threadpool(self._read, auction_id)
        except (DatabaseUnavailableError, SQLAlchemyError) as exc:
            log.debug("an auction's patrons could not be read: %s", exc)  # served as a watcher
            return False
        if len(self._tokens) >= MAX_AUCTIONS and auction_id not in self._tokens:
            self._tokens.clear()
        self._tokens[auction_id] = (time.monotonic(), tokens)
        return digest in tokens

    def _read(self, auction_id: int) -> frozenset[str]:
        with self._database.transaction(write=False) as connection:
            return crud.patron_tokens(connection, auction_id=auction_id)
