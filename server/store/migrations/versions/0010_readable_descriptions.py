"""Readable descriptions: a manifest's ``description`` holds no control character but tab and
line breaks, and no bidirectional override (the manifest's schema refuses them from now on).

A description stored before (a stored version's, a pending upload's) loses those characters,
so that every stored manifest still reads as a manifest.

Revision ID: 0010
Revises: 0009
"""

from __future__ import annotations

import re
from typing import Any

import sqlalchemy as sa
from alembic import op

revision = "0010"
down_revision = "0009"
branch_labels = None
depends_on = None

UNREADABLE = re.compile(
    "[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]"
)
"""What the schema refuses in a description (as ``agents.manifest`` did at this revision)."""

CHUNK = 500
"""Manifests read at once."""
TABLES = (
    sa.table("model_versions", sa.column("id", sa.Integer), sa.column("manifest", sa.JSON)),
    sa.table("fine_tune_answers", sa.column("id", sa.Integer), sa.column("manifest", sa.JSON)),
)


def _cleaned(manifest: Any) -> dict[str, Any] | None:
    """The manifest with a readable description, or None when it has one already."""
    if not isinstance(manifest, dict):
        return None
    description = manifest.get("description")
    if not isinstance(description, str) or not UNREADABLE.search(description):
        return None
    return {**manifest, "description": UNREADABLE.sub("", description)}


def upgrade() -> None:
    connection = op.get_bind()
    for table in TABLES:
        # Whole manifests, a chunk at a time: SQLite's JSON functions end a string at a NUL.
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
