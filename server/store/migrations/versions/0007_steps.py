"""Auctions moved by steps: when the next step is due; pending round uploads keep their manifest.

Revision ID: 0007
Revises: 0006
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.tables import UtcDateTime

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("auctions", sa.Column("next_step_at", UtcDateTime(), nullable=True))
    op.create_index("ix_auctions_next_step_at", "auctions", ["next_step_at"])
    # Unfinished auctions of an earlier version are due at once.
    op.execute(
        "UPDATE auctions SET next_step_at = updated_at WHERE status IN ('pending', 'running')"
    )
    op.add_column("fine_tune_answers", sa.Column("manifest", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("fine_tune_answers") as batch:
        batch.drop_column("manifest")
    op.drop_index("ix_auctions_next_step_at", table_name="auctions")
    with op.batch_alter_table("auctions") as batch:
        batch.drop_column("next_step_at")
