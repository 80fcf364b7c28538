"""Remote fine-tuning rounds: auction settings, round and answer tables, version lineage.

Revision ID: 0002
Revises: 0001
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.tables import UtcDateTime

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def _add_reference(table: str, column: str, target: str) -> None:
    """A nullable integer column referring to ``target.id``, added in place: SQLite takes the
    reference inline (it cannot add constraints later, and copying a table that other tables
    refer to would break their references)."""
    if op.get_bind().dialect.name == "sqlite":
        op.execute(f"ALTER TABLE {table} ADD COLUMN {column} INTEGER REFERENCES {target} (id)")
        return
    op.add_column(table, sa.Column(column, sa.Integer(), nullable=True))
    op.create_foreign_key(op.f(f"fk_{table}_{column}_{target}"), table, target, [column], ["id"])


def upgrade() -> None:
    op.add_column(
        "auctions",
        sa.Column("fine_tune_mode", sa.String(length=8), nullable=False, server_default="server"),
    )
    op.add_column(
        "auctions", sa.Column("fine_tune_rounds", sa.Integer(), nullable=False, server_default="4")
    )
    op.add_column(
        "auctions", sa.Column("round_deadline_s", sa.Float(), nullable=False, server_default="10")
    )
    _add_reference("model_versions", "parent_id", "model_versions")
    _add_reference("model_versions", "auction_id", "auctions")
    op.add_column("model_versions", sa.Column("round", sa.Integer(), nullable=True))
    _add_reference("auction_patrons", "current_model_id", "model_versions")
    op.create_table(
        "fine_tune_rounds",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("auction_id", sa.Integer(), nullable=False),
        sa.Column("round", sa.Integer(), nullable=False),
        sa.Column("iteration", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(length=8), nullable=False),
        sa.Column("opened_at", UtcDateTime(), nullable=False),
        sa.Column("deadline", UtcDateTime(), nullable=False),
        sa.Column("closed_at", UtcDateTime(), nullable=True),
        sa.Column("rows", sa.JSON(), nullable=False),
        sa.Column("fine_tune_seed", sa.BigInteger(), nullable=False),
        sa.Column("augmentation_seed", sa.BigInteger(), nullable=False),
        sa.Column("asked", sa.JSON(), nullable=False),
        sa.Column("bytes_published", sa.BigInteger(), nullable=False),
        sa.ForeignKeyConstraint(
            ["auction_id"], ["auctions.id"], name=op.f("fk_fine_tune_rounds_auction_id_auctions")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_fine_tune_rounds")),
        sa.UniqueConstraint("auction_id", "round", name=op.f("uq_fine_tune_rounds_auction_id")),
    )
    op.create_table(
        "fine_tune_answers",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("round_id", sa.Integer(), nullable=False),
        sa.Column("position", sa.Integer(), nullable=False),
        sa.Column("outcome", sa.String(length=8), nullable=False),
        sa.Column("model_id", sa.Integer(), nullable=False),
        sa.Column("uploaded_id", sa.Integer(), nullable=True),
        sa.Column("body_sha256", sa.String(length=64), nullable=True),
        sa.Column("answer", sa.JSON(none_as_null=True), nullable=True),
        sa.Column("bytes_in", sa.BigInteger(), nullable=False),
        sa.Column("bytes_out", sa.BigInteger(), nullable=False),
        sa.Column("created_at", UtcDateTime(), nullable=False),
        sa.ForeignKeyConstraint(
            ["round_id"],
            ["fine_tune_rounds.id"],
            name=op.f("fk_fine_tune_answers_round_id_fine_tune_rounds"),
        ),
        sa.ForeignKeyConstraint(
            ["model_id"],
            ["model_versions.id"],
            name=op.f("fk_fine_tune_answers_model_id_model_versions"),
        ),
        sa.ForeignKeyConstraint(
            ["uploaded_id"],
            ["model_versions.id"],
            name=op.f("fk_fine_tune_answers_uploaded_id_model_versions"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_fine_tune_answers")),
        sa.UniqueConstraint("round_id", "position", name=op.f("uq_fine_tune_answers_round_id")),
    )


def downgrade() -> None:
    op.drop_table("fine_tune_answers")
    op.drop_table("fine_tune_rounds")
    with op.batch_alter_table("auction_patrons") as batch:
        batch.drop_column("current_model_id")
    with op.batch_alter_table("model_versions") as batch:
        batch.drop_column("round")
        batch.drop_column("auction_id")
        batch.drop_column("parent_id")
    with op.batch_alter_table("auctions") as batch:
        batch.drop_column("round_deadline_s")
        batch.drop_column("fine_tune_rounds")
        batch.drop_column("fine_tune_mode")
