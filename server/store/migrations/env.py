"""Alembic environment: migrates the database named in the config (see ``server.store.db``)."""

from __future__ import annotations

from alembic import context

from server.store.db import is_sqlite, make_engine
from server.store.tables import Base

url = context.config.get_main_option("sqlalchemy.url")
if url is None:
    raise RuntimeError("sqlalchemy.url is not set in the Alembic config")


def run_offline() -> None:
    """Emit SQL to stdout (``alembic upgrade --sql``)."""
    context.configure(url=url, target_metadata=Base.metadata, literal_binds=True)
    with context.begin_transaction():
        context.run_migrations()


def run_online(database_url: str) -> None:
    """Migrate a live database."""
    engine = make_engine(database_url, create=True)  # a first start creates the SQLite file
    try:
        with engine.connect() as connection:
            context.configure(
                connection=connection,
                target_metadata=Base.metadata,
                render_as_batch=is_sqlite(database_url),  # SQLite alters tables by copying
            )
            with context.begin_transaction():
                context.run_migrations()
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_offline()
else:
    run_online(url)
