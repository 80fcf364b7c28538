"""Leases: the API process that plays an auction or runs a job, and until when.

Revision ID: 0004
Revises: 0003
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.tables import LEASE_OWNER_LENGTH, UtcDateTime

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

TABLES = ("auctions", "jobs")


def upgrade() -> None:
    for table in TABLES:
        op.add_column(
            table, sa.Column("lease_owner", sa.String(length=LEASE_OWNER_LENGTH), nullable=True)
        )
        op.add_column(table, sa.Column("lease_expires", UtcDateTime(), nullable=True))


def downgrade() -> None:
    for table in TABLES:
        with op.batch_alter_table(table) as batch:
            batch.drop_column("lease_expires")
            batch.drop_column("lease_owner")
