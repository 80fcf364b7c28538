"""When an outage's time was last given back to a round (replicas give it once).

Revision ID: 0017
Revises: 0016
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.tables import UtcDateTime

revision = "0017"
down_revision = "0016"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("fine_tune_rounds", sa.Column("given_back_at", UtcDateTime(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("fine_tune_rounds") as batch:
        batch.drop_column("given_back_at")
