"""Alembic environment: migrates the database named in the config (see ``server.store.db``)."""

from __future__ import annotations

from alembic import context

from server.store import db
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
    """Migrate a live database.

    SQLite alters a table by copying it to a new one and dropping the old, which its foreign
    keys refuse while other rows reference the old one: they are off while the migrations run
    (a pragma that takes effect only outside a transaction), and the rows are checked against
    them before the migrations commit."""
    sqlite = is_sqlite(database_url)
    engine = make_engine(database_url, create=True)  # a first start creates the SQLite file
    try:
        with engine.connect() as connection:
            driver = connection.connection.driver_connection
            if sqlite and driver is not None:  # on the driver's: SQLAlchemy would BEGIN first
                driver.execute("PRAGMA foreign_keys=OFF")
            if not sqlite:  # fail, rather than queue the old servers' queries behind an ALTER
                waited = round(db.MIGRATION_LOCK_TIMEOUT_S * 1000)
                connection.exec_driver_sql(f"SET lock_timeout = {waited}")  # for the session
                connection.commit()  # ends the transaction SQLAlchemy began for the SET
            context.configure(
                connection=connection,
                target_metadata=Base.metadata,
                render_as_batch=sqlite,  # SQLite alters tables by copying
            )
            with context.begin_transaction():
                context.run_migrations()
                if sqlite:
                    broken = connection.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
                    if broken:
                        raise RuntimeError(
                            f"the migrated database breaks its foreign keys: {broken[:5]}"
                        )
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_offline()
else:
    run_online(url)
