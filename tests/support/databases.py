"""Throw-away databases for a run: a SQLite file, or a new randomly named PostgreSQL database
on the loopback server (trust authentication), dropped afterwards."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from sqlalchemy import create_engine, text
from sqlalchemy.exc import OperationalError

LOCAL_POSTGRES = "127.0.0.1:5432"
POSTGRES_USERS = ("postgres", "root")
BACKENDS = ["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)]
"""The parameters of a fixture that runs on each backend (PostgreSQL marked ``postgres``)."""


def postgres_admin_url(server: str = LOCAL_POSTGRES) -> str | None:
    """A URL to the ``postgres`` database of ``server`` that accepts us, or None."""
    for user in POSTGRES_USERS:
        url = f"postgresql+psycopg://{user}@{server}/postgres"
        engine = create_engine(url, isolation_level="AUTOCOMMIT")
        try:
            with engine.connect() as conn:
                conn.execute(text("select 1"))
            return url
        except OperationalError:
            continue
        finally:
            engine.dispose()
    return None


@contextmanager
def throwaway_postgres(admin_url: str) -> Iterator[str]:
    """A new randomly named PostgreSQL database for the duration of the block, then dropped."""
    name = f"srd_tmp_{uuid.uuid4().hex[:12]}"
    engine = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield admin_url.rsplit("/", 1)[0] + f"/{name}"
    finally:
        with engine.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        engine.dispose()


def postgres_database() -> Iterator[str]:
    """A throw-away PostgreSQL database, or the test skipped when the server is down."""
    admin_url = postgres_admin_url()
    if admin_url is None:
        pytest.skip(f"PostgreSQL unreachable on {LOCAL_POSTGRES}; .ci/run starts it")
    with throwaway_postgres(admin_url) as url:
        yield url


def fresh_database(backend: str, folder: Path) -> Iterator[str]:
    """A fresh empty database of ``backend`` ("sqlite": a file in ``folder``; "postgresql")."""
    if backend == "sqlite":
        yield f"sqlite:///{folder / 'srd.db'}"
    else:
        yield from postgres_database()
