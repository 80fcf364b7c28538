"""Vote explanations: each committed iteration keeps every voter's neurons on the row it voted
on (null for iterations committed before this revision).

Revision ID: 0008
Revises: 0007
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("auction_iterations", sa.Column("explanations", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("auction_iterations") as batch:
        batch.drop_column("explanations")
