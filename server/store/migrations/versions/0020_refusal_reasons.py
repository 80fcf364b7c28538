"""The reasons a server-mode auction's re-screening refused a patron's fine-tuning: the
screener's findings, each ``{rule, neuron, message}``, kept with the refusal so that the
weights' page can say which rule reverted it. Refusals stored before keep none (null).

Revision ID: 0020
Revises: 0019
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0020"
down_revision = "0019"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("tuned_weights", sa.Column("reasons", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("tuned_weights") as batch:
        batch.drop_column("reasons")
