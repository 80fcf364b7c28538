"""Whose round requests are a patron's: the round sockets and long polls of an auction keep a
share for the participants whose models bid in it, so that others (watchers, or many addresses
each within its own share) cannot take every slot from them (``server.auctions.sockets``,
``server.live.rounds``)."""

from __future__ import annotations

import logging

from sqlalchemy.exc import SQLAlchemyError
from starlette.concurrency import run_in_threadpool

from server.api.security import hash_token
from server.store import crud
from server.store.db import Database, DatabaseUnavailableError

log = logging.getLogger("srd.patrons")

MAX_KNOWN = 100_000
"""(auction, token) pairs remembered as patrons (forgotten all at once past it)."""


class PatronCheck:
    """Whether a bearer token is a participant's with a patron in an auction: one indexed read,
    remembered when it is (a patron stays one for the auction's life)."""

    def __init__(self, database: Database) -> None:
        self._database = database
        self._known: set[tuple[int, str]] = set()

    async def is_patron(self, auction_id: int, token: str | None) -> bool:
        if not token:
            return False
        key = (auction_id, hash_token(token))
        if key in self._known:
            return True
        try:
            found = await run_in_threadpool(self._look_up, *key)
        except (DatabaseUnavailableError, SQLAlchemyError) as exc:
            log.debug("a patron could not be looked up: %s", exc)  # served as a watcher
            return False
        if found:
            if len(self._known) >= MAX_KNOWN:
                self._known.clear()
            self._known.add(key)
        return found

    def _look_up(self, auction_id: int, digest: str) -> bool:
        with self._database.session(write=False) as session:
            return crud.is_patron(session, auction_id=auction_id, token_hash=digest)
