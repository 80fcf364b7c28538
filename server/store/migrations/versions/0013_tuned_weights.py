"""Tuned weights: a server-mode auction records each patron's fine-tuning inside the market,
kept or refused by its re-screening, with the weights it kept, so that every vote can be traced
to the weights that cast it (``GET /auctions/{id}/iterations/{n}/votes/{model_id}/weights``).

The auctions created before keep no such rows (``keeps_tuned_weights`` false): their votes
after a fine-tuning inside the market say that the weights behind them are not known.

Revision ID: 0013
Revises: 0012
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0013"
down_revision = "0012"
branch_labels = None
depends_on = None


def upgrade() -> None:
    # Every auction created from now on keeps them; those already there kept none.
    op.add_column(
        "auctions",
        sa.Column("keeps_tuned_weights", sa.Boolean(), nullable=False, server_default=sa.true()),
    )
    op.execute(
        sa.table("auctions", sa.column("keeps_tuned_weights", sa.Boolean))
        .update()
        .values(keeps_tuned_weights=False)
    )
    op.create_table(
        "tuned_weights",
        sa.Column("auction_id", sa.Integer(), nullable=False),
        sa.Column("model_id", sa.Integer(), nullable=False),
        sa.Column("iteration", sa.Integer(), nullable=False),
        sa.Column("kept", sa.Boolean(), nullable=False),
        sa.Column("manifest", sa.JSON(), nullable=True),
        sa.ForeignKeyConstraint(
            ["auction_id"], ["auctions.id"], name="fk_tuned_weights_auction_id_auctions"
        ),
        sa.ForeignKeyConstraint(
            ["model_id"], ["model_versions.id"], name="fk_tuned_weights_model_id_model_versions"
        ),
        sa.PrimaryKeyConstraint("auction_id", "model_id", "iteration", name="pk_tuned_weights"),
    )


def downgrade() -> None:
    op.drop_table("tuned_weights")
    with op.batch_alter_table("auctions") as batch:
        batch.drop_column("keeps_tuned_weights")
