"""The live-update signal: every commit that changes what an event stream, a long poll or a
round socket shows says so on PostgreSQL's ``LISTEN``/``NOTIFY`` channel, in its own
transaction (delivered once it commits, dropped if it rolls back). API processes listen
(``server.live.source``); SQLite has no such channel, its API process polls instead."""

from __future__ import annotations

from typing import Literal

from sqlalchemy import func, select
from sqlalchemy.orm import Session

LIVE_CHANNEL = "srd_live"
LiveKind = Literal["auction", "job"]


def notify_change(session: Session, *, kind: LiveKind, row_id: int) -> None:
    """Announce, with this transaction's commit, that the auction or job ``row_id`` changed
    (payload ``<kind>:<id>``); nothing on SQLite."""
    if session.get_bind().dialect.name == "postgresql":
        session.execute(select(func.pg_notify(LIVE_CHANNEL, f"{kind}:{row_id}")))
