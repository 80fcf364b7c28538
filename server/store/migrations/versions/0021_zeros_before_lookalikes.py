"""Look-alike names: zeros or Os leading a part that reads as a number are left out whatever
digit-like character follows, so ``honest-0l`` and ``Honest-OI`` read as ``honest-1``, as
``Honest-01`` already did (``server.store.tables.participant_key``).

Every stored participant's key is computed again, as revisions 0015 and 0019 did:
participants stored before whose names now fold to one key keep working under their exact
names.

Revision ID: 0021
Revises: 0020
"""

from __future__ import annotations

from alembic import op

from server.store.tables import rekey_participants

revision = "0021"
down_revision = "0020"
branch_labels = None
depends_on = None


def upgrade() -> None:
    rekey_participants(op.get_bind())


def downgrade() -> None:
    """The keys stay as they are: every one is still unique."""
