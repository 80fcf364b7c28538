"""Reviews: a model version's status (accepted | refused | held) and the screener's evidence,
and the audit log of inspectors' decisions and participants' appeals (``reviews``).

Every stored version gets the status its ``accepted`` column says (nothing was held before);
its evidence stays null (it was not kept).

Revision ID: 0009
Revises: 0008
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.tables import UtcDateTime

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None

model_versions = sa.table(
    "model_versions",
    sa.column("accepted", sa.Boolean),
    sa.column("status", sa.String),
)


def upgrade() -> None:
    op.add_column("model_versions", sa.Column("status", sa.String(length=8), nullable=True))
    op.add_column("model_versions", sa.Column("evidence", sa.JSON(), nullable=True))
    op.execute(
        model_versions.update().values(
            status=sa.case((model_versions.c.accepted, "accepted"), else_="refused")
        )
    )
    with op.batch_alter_table("model_versions") as batch:
        batch.alter_column("status", existing_type=sa.String(length=8), nullable=False)
        batch.create_index("ix_model_versions_status", ["status"])
    op.create_table(
        "reviews",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("model_id", sa.Integer(), nullable=False),
        sa.Column("decision", sa.String(length=8), nullable=False),
        sa.Column("inspector", sa.String(length=64), nullable=False),
        sa.Column("note", sa.Text(), nullable=False),
        sa.Column("at", UtcDateTime(), nullable=False),
        sa.Column("evidence", sa.JSON(), nullable=True),
        sa.ForeignKeyConstraint(
            ["model_id"],
            ["model_versions.id"],
            name="fk_reviews_model_id_model_versions",
        ),
        sa.PrimaryKeyConstraint("id", name="pk_reviews"),
    )
    op.create_index("ix_reviews_model_id", "reviews", ["model_id"])


def downgrade() -> None:
    op.drop_index("ix_reviews_model_id", table_name="reviews")
    op.drop_table("reviews")
    with op.batch_alter_table("model_versions") as batch:
        batch.drop_index("ix_model_versions_status")
        batch.drop_column("evidence")
        batch.drop_column("status")
