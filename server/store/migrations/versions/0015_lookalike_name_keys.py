"""Look-alike names: a participant's name key also makes one the characters a reader takes for
one another (I, l and 1; O and 0; rn and m; the separators), so that ``honest-I`` cannot pass
for ``honest-1`` (``server.store.tables.participant_key``).

Every stored participant's key is computed again. Participants stored before whose names now
fold to one key keep working under their exact names, as revision 0006 did for case: the first
registered keeps the key, each later one gets it suffixed with ``#<id>`` (which no name can
fold to).

Revision ID: 0015
Revises: 0014
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.store.tables import participant_key

revision = "0015"
down_revision = "0014"
branch_labels = None
depends_on = None

participants = sa.table(
    "participants",
    sa.column("id", sa.Integer),
    sa.column("name", sa.String),
    sa.column("name_key", sa.String),
)


def upgrade() -> None:
    connection = op.get_bind()
    rows = connection.execute(
        sa.select(participants.c.id, participants.c.name).order_by(participants.c.id)
    ).all()
    taken: set[str] = set()
    keys = []
    for participant_id, name in rows:
        key = participant_key(name)
        if key in taken:
            key = f"{key}#{participant_id}"
        taken.add(key)
        keys.append({"row_id": participant_id, "key": key})
    set_key = (
        participants.update()
        .where(participants.c.id == sa.bindparam("row_id"))
        .values(name_key=sa.bindparam("key"))
    )
    if keys:  # through keys no name folds to first, so that no update meets a unique key
        connection.execute(
            set_key, [{"row_id": k["row_id"], "key": f"#{k['row_id']}"} for k in keys]
        )
        connection.execute(set_key, keys)


def downgrade() -> None:
    """The keys stay as they are: every one is still unique."""
