"""Participant name keys: names that differ only in case or Unicode form are one participant.

Adds ``participants.name_key`` (``server.store.tables.participant_key`` of the name), fills it
for the stored participants and makes it unique. Participants stored before whose names already
collide keep working under their exact names: the first registered keeps the key, each later
one gets its key suffixed with ``#<id>`` (which no name can fold to).

Revision ID: 0006
Revises: 0005
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.tables import NAME_KEY_LENGTH, rekey_participants

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column(
        "participants", sa.Column("name_key", sa.String(length=NAME_KEY_LENGTH), nullable=True)
    )
    rekey_participants(op.get_bind())
    with op.batch_alter_table("participants") as batch:
        batch.alter_column(
            "name_key", existing_type=sa.String(length=NAME_KEY_LENGTH), nullable=False
        )
        batch.create_unique_constraint("uq_participants_name_key", ["name_key"])


def downgrade() -> None:
    with op.batch_alter_table("participants") as batch:
        batch.drop_constraint("uq_participants_name_key", type_="unique")
        batch.drop_column("name_key")
