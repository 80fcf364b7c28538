"""Quotas: the events they count (versions, registrations, screener refusals).

Revision ID: 0003
Revises: 0002
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.tables import UtcDateTime

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "rate_events",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("subject", sa.String(length=160), nullable=False),
        sa.Column("kind", sa.String(length=16), nullable=False),
        sa.Column("created_at", UtcDateTime(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_rate_events")),
    )
    op.create_index(
        "ix_rate_events_subject_kind_at", "rate_events", ["subject", "kind", "created_at"]
    )
    op.create_index(op.f("ix_rate_events_created_at"), "rate_events", ["created_at"])


def downgrade() -> None:
    op.drop_index(op.f("ix_rate_events_created_at"), table_name="rate_events")
    op.drop_index("ix_rate_events_subject_kind_at", table_name="rate_events")
    op.drop_table("rate_events")
