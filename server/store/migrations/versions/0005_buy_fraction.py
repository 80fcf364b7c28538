"""The market's buy-fraction rule of each auction ("all", the paper's, for those before it).

Revision ID: 0005
Revises: 0004
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column(
        "auctions",
        sa.Column("buy_fraction", sa.String(length=8), nullable=False, server_default="all"),
    )


def downgrade() -> None:
    with op.batch_alter_table("auctions") as batch:
        batch.drop_column("buy_fraction")
