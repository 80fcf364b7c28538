"""The live-update signal: every commit that changes what an event stream, a long poll or a
round socket shows says so on PostgreSQL's ``LISTEN``/``NOTIFY`` channel, in its own
transaction (delivered once it commits, dropped if it rolls back). API processes listen
(``server.live.source``); SQLite has no such channel, its API process polls instead."""

from __future__ import annotations

from typing import Literal

from sqlalchemy import Connection, func, select
from sqlalchemy.orm import Session

LIVE_CHANNEL = "srd_live"
LiveKind = Literal["auction", "job"]


def notify_change(db: Session | Connection, *, kind: LiveKind, row_id: int) -> None:
    """Announce, with this transaction's commit (``db``: its session or connection), that the
    auction or job ``row_id`` changed (payload ``<kind>:<id>``); nothing on SQLite."""
    _notify(db, f"{kind}:{row_id}")


def notify_due(db: Session | Connection, *, kind: LiveKind) -> None:
    """Announce, with this transaction's commit, that a row of ``kind`` is due to be played
    now (payload ``due:<kind>``): the runner of every replica looks for work (within
    ``server.live.source.DUE_DELAY_S``), so one with a free worker plays it while this
    replica's workers are all busy (nothing on SQLite, where one server runs)."""
    _notify(db, f"due:{kind}")


def _notify(db: Session | Connection, payload: str) -> None:
    dialect = db.dialect if isinstance(db, Connection) else db.get_bind().dialect
    if dialect.name == "postgresql":
        db.execute(select(func.pg_notify(LIVE_CHANNEL, payload)))
