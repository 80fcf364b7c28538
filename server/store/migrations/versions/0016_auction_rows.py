"""Item rows per auction: 64, the reference's (every auction before), or the paper's 16.

Revision ID: 0016
Revises: 0015
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0016"
down_revision = "0015"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column(
        "auctions", sa.Column("n_rows", sa.Integer(), nullable=False, server_default="64")
    )


def downgrade() -> None:
    with op.batch_alter_table("auctions") as batch:
        batch.drop_column("n_rows")
