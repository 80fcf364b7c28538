"""Visible descriptions: a manifest's ``description`` holds no invisible character either (a
zero-width space, a soft hyphen, a Hangul filler, tag characters that spell hidden text...),
which the manifest's schema refuses from now on, as it refused control characters and
bidirectional overrides from revision 0010 on: text an inspector reads shows all it says.

A description stored before (a stored version's, a pending upload's) loses those characters,
so that every stored manifest still reads as a manifest.

Revision ID: 0014
Revises: 0013
"""

from __future__ import annotations

import re
from typing import Any

import sqlalchemy as sa
from alembic import op

revision = "0014"
down_revision = "0013"
branch_labels = None
depends_on = None

INVISIBLE = re.compile(
    "[\xad\u115f\u1160\u180e\u200b\u2060-\u2064\u3164\uffa0\ufeff\ufff9-\ufffb"
    "\U000e0000-\U000e03ff]"
)
"""What the schema refuses in a description from this revision on, beyond revision 0010's."""

CHUNK = 500
"""Manifests read at once."""
TABLES = (
    sa.table("model_versions", sa.column("id", sa.Integer), sa.column("manifest", sa.JSON)),
    sa.table("fine_tune_answers", sa.column("id", sa.Integer), sa.column("manifest", sa.JSON)),
)


def _cleaned(manifest: Any) -> dict[str, Any] | None:
    """The manifest with a visible description, or None when it has one already."""
    if not isinstance(manifest, dict):
        return None
    description = manifest.get("description")
    if not isinstance(description, str) or not INVISIBLE.search(description):
        return None
    return {**manifest, "description": INVISIBLE.sub("", description)}


def upgrade() -> None:
    connection = op.get_bind()
    for table in TABLES:
        ids = list(connection.scalars(sa.select(table.c.id).order_by(table.c.id)))
        for start in range(0, len(ids), CHUNK):
            chunk = ids[start : start + CHUNK]
            rows = connection.execute(
                sa.select(table.c.id, table.c.manifest).where(table.c.id.in_(chunk))
            ).all()
            for row_id, manifest in rows:
                cleaned = _cleaned(manifest)
                if cleaned is not None:
                    connection.execute(
                        table.update().where(table.c.id == row_id).values(manifest=cleaned)
                    )


def downgrade() -> None:
    """Nothing to undo: the characters removed are not kept."""
