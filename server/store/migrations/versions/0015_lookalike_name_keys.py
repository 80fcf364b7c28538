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

from alembic import op

from server.store.tables import rekey_participants

revision = "0015"
down_revision = "0014"
branch_labels = None
depends_on = None


def upgrade() -> None:
    rekey_participants(op.get_bind())


def downgrade() -> None:
    """The keys stay as they are: every one is still unique."""
