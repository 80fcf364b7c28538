"""An auction's enrollment: until when participants may add their models as patrons
(``POST /auctions/{id}/patrons``); null once its patrons are fixed.

Revision ID: 0012
Revises: 0011
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.tables import UtcDateTime

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("auctions", sa.Column("enroll_until", UtcDateTime(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("auctions") as batch:
        batch.drop_column("enroll_until")
