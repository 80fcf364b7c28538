"""The leases of background work (``server.work.runner``): which unfinished auctions and jobs
are free to claim, claiming, renewing and releasing them. Every function takes the table
(``Auction`` or ``Job``) and the statuses of its unfinished rows."""

from __future__ import annotations

from collections.abc import Collection, Sequence
from datetime import datetime
from typing import Any

from sqlalchemy import ColumnElement, func, or_, select, text, update
from sqlalchemy.orm import Session

from server.store.tables import Auction, Job

Table = type[Auction] | type[Job]


def _unleased(table: Table, unfinished: Sequence[str], now: datetime) -> list[ColumnElement[bool]]:
    """Unfinished rows with no lease or an expired one."""
    return [
        table.status.in_(unfinished),
        or_(table.lease_owner.is_(None), table.lease_expires < now),
    ]


def claimable(
    session: Session,
    *,
    table: Table,
    unfinished: Sequence[str],
    due: Any,
    now: datetime,
    held: Collection[int],
    limit: int,
    lock: bool,
) -> list[int]:
    """Up to ``limit`` unfinished rows with no lease or an expired one, due by ``now``
    (``due``: the column of their due time, or None), except the rows ``held``: the longest due
    first (those due at once before them), then the oldest; with ``lock``, locked until commit,
    skipping the rows another transaction locked."""
    order = (table.id,) if due is None else (due.is_not(None), due, table.id)
    query = (
        select(table.id)
        .where(*_unleased(table, unfinished, now))
        .where(table.id.notin_(held))
        .order_by(*order)
        .limit(limit)
    )
    if due is not None:
        query = query.where(or_(due.is_(None), due <= now))
    if lock:
        query = query.with_for_update(skip_locked=True)
    return list(session.scalars(query))


def earliest_due(
    session: Session, *, table: Table, unfinished: Sequence[str], due: Any, now: datetime
) -> datetime | None:
    """The earliest due time after ``now`` of an unfinished row without a live lease."""
    earliest: datetime | None = session.scalar(
        select(func.min(due)).where(*_unleased(table, unfinished, now)).where(due > now)
    )
    return earliest


def expired_owners(
    session: Session,
    *,
    table: Table,
    unfinished: Sequence[str],
    now: datetime,
    other_than: str,
    row_ids: Collection[int],
) -> list[str]:
    """The owners, but ``other_than``, of the unfinished rows ``row_ids`` whose lease has
    expired."""
    query = (
        select(table.lease_owner)
        .distinct()
        .where(
            table.id.in_(row_ids),
            table.status.in_(unfinished),
            table.lease_expires < now,
            table.lease_owner.is_not(None),
            table.lease_owner != other_than,
        )
    )
    return [owner for owner in session.scalars(query) if owner is not None]


def end_sessions(session: Session, names: Sequence[str]) -> int:
    """End the other PostgreSQL sessions of this database named ``names`` (their
    ``application_name``): a replica frozen inside a transaction keeps its row locks until its
    connection breaks, which takes hours when its host is still up; how many were ended."""
    ended = session.execute(
        text(
            "SELECT count(*) FILTER (WHERE pg_terminate_backend(pid)) FROM pg_stat_activity "
            "WHERE datname = current_database() AND pid <> pg_backend_pid() "
            "AND application_name = ANY(:names)"
        ),
        {"names": list(names)},
    ).scalar_one()
    return int(ended)


def take_leases(
    session: Session,
    *,
    table: Table,
    row_ids: Collection[int],
    owner: str,
    expires: datetime | None,
) -> None:
    """Lease the rows to ``owner`` until ``expires`` (None: for ever)."""
    session.execute(
        update(table).where(table.id.in_(row_ids)).values(lease_owner=owner, lease_expires=expires)
    )


def renew_leases(
    session: Session,
    *,
    table: Table,
    unfinished: Sequence[str],
    row_ids: Collection[int],
    owner: str,
    expires: datetime,
) -> set[int]:
    """Extend to ``expires`` the leases ``owner`` still holds on unfinished rows among
    ``row_ids``; the rows renewed."""
    return set(
        session.scalars(
            update(table)
            .where(table.id.in_(row_ids))
            .where(table.lease_owner == owner)
            .where(table.status.in_(unfinished))
            .values(lease_expires=expires)
            .returning(table.id)
        )
    )


def stopped_elsewhere(
    session: Session, *, table: Table, unfinished: Sequence[str], row_ids: Collection[int]
) -> set[int]:
    """Among rows whose lease could not be renewed, those whose tasks must stop: cancelled,
    or still unfinished (the lease is someone else's now, or nobody's). A row that ended by
    its own task's commit, finished or failed, is left to that task."""
    return set(
        session.scalars(
            select(table.id)
            .where(table.id.in_(row_ids))
            .where(or_(table.status == "cancelled", table.status.in_(unfinished)))
        )
    )


def release_leases(session: Session, *, table: Table, row_ids: Collection[int], owner: str) -> None:
    """Drop the leases ``owner`` holds on ``row_ids``."""
    session.execute(
        update(table)
        .where(table.id.in_(row_ids))
        .where(table.lease_owner == owner)
        .values(lease_owner=None, lease_expires=None)
    )


def clear_leases(session: Session, *, table: Table) -> None:
    """Drop every lease of the table (a SQLite server starting: nobody else can hold one)."""
    session.execute(update(table).values(lease_owner=None, lease_expires=None))


def schema_revision(session: Session) -> str | None:
    """The schema revision the database is at now (a newer release may have migrated it)."""
    revision = session.scalar(text("SELECT version_num FROM alembic_version"))
    return None if revision is None else str(revision)


def progress_of(session: Session, *, column: Any, row_id: int) -> Any:
    """A row's progress as ``column`` (of its table) reads it now: None if it is gone."""
    return session.scalar(select(column).where(column.class_.id == row_id))
