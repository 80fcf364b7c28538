"""The keyset order of the lists: by id, newest or oldest first, from after a cursor."""

from __future__ import annotations

from typing import Any, Literal

from sqlalchemy import Select
from sqlalchemy.orm import InstrumentedAttribute

ListOrder = Literal["newest", "oldest"]
"""newest: ids falling (the default); oldest: ids rising. Ids only grow, so this is time."""


def keyset(
    query: Select[Any],
    id_column: InstrumentedAttribute[int],
    *,
    cursor: int | None,
    order: ListOrder,
) -> Select[Any]:
    """``query`` ordered by ``id_column`` in ``order``, holding only the rows after ``cursor``
    (the last id of the previous page) in that order."""
    if order == "oldest":
        query = query.order_by(None).order_by(id_column.asc())
        return query if cursor is None else query.where(id_column > cursor)
    query = query.order_by(None).order_by(id_column.desc())
    return query if cursor is None else query.where(id_column < cursor)
