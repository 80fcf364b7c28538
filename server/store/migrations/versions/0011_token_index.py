"""An index on participants' token hashes: the per-client limits look a token up before
counting a request against it.

Revision ID: 0011
Revises: 0010
"""

from __future__ import annotations

from alembic import op

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_index("ix_participants_token_hash", "participants", ["token_hash"])


def downgrade() -> None:
    op.drop_index("ix_participants_token_hash", table_name="participants")
