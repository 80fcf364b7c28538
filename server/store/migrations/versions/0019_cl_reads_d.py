"""Look-alike names: ``cl`` reads as ``d`` (``clave`` passed for ``dave`` in the web view and
the lists), and so do ``c1`` and ``cI``, which already read as ``cl``
(``server.store.tables.participant_key``).

Every stored participant's key is computed again, as revision 0015 did: participants stored
before whose names now fold to one key keep working under their exact names.

Revision ID: 0019
Revises: 0018
"""

from __future__ import annotations

from alembic import op

from server.store.tables import rekey_participants

revision = "0019"
down_revision = "0018"
branch_labels = None
depends_on = None


def upgrade() -> None:
    rekey_participants(op.get_bind())


def downgrade() -> None:
    """The keys stay as they are: every one is still unique."""
