"""No smuggled text: a manifest's ``description`` holds no variation selector but the emoji's
two, no run of three zero-width joiners or selectors, and none of the other invisible formats
(the combining grapheme joiner, Mongolian selectors, deprecated and unassigned formats, marks
set before a number, the object replacement mark, Egyptian and musical format controls, the
default-ignorable planes), which the manifest's schema refuses from now on: 74 variation
selectors after "Honest." spelt an instruction a reader of the text never saw.

A description stored before (a stored version's, a pending upload's) loses those characters,
and its runs are cut to two, so that every stored manifest still reads as a manifest.

Revision ID: 0018
Revises: 0017
"""

from __future__ import annotations

import re
from typing import Any

import sqlalchemy as sa
from alembic import op

revision = "0018"
down_revision = "0017"
branch_labels = None
depends_on = None

INVISIBLE = re.compile(
    "[\u034f\u17b4\u17b5\u180b-\u180d\u180f\u2065\u206a-\u206f\ufe00-\ufe0d"
    "\u0600-\u0605\u06dd\u070f\u0890\u0891\u08e2\ufffc\ufff0-\ufff8"
    "\U000110bd\U000110cd\U00013430-\U0001343f\U0001bca0-\U0001bca3\U0001d173-\U0001d17a"
    "\U000e0400-\U000e0fff]"
)
"""What the schema refuses in a description from this revision on, beyond revision 0014's."""
RUN = re.compile("([\u200c\u200d\ufe0e\ufe0f]{2})[\u200c\u200d\ufe0e\ufe0f]+")
"""A run of joiners and selectors: its first two are kept."""

CHUNK = 500
"""Manifests read at once."""
TABLES = (
    sa.table("model_versions", sa.column("id", sa.Integer), sa.column("manifest", sa.JSON)),
    sa.table("fine_tune_answers", sa.column("id", sa.Integer), sa.column("manifest", sa.JSON)),
)


def _cleaned(manifest: Any) -> dict[str, Any] | None:
    """The manifest with a plain description, or None when it has one already."""
    if not isinstance(manifest, dict):
        return None
    description = manifest.get("description")
    if not isinstance(description, str):
        return None
    plain = RUN.sub(r"\1", INVISIBLE.sub("", description))
    return None if plain == description else {**manifest, "description": plain}


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
