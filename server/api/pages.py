"""Pagination of the lists: the ``limit`` and ``cursor`` query parameters.

Lists are newest first and ids only grow, so a page is the rows below an id: the cursor of the
next page is the id of the last row of this one (``next_cursor``), and every cursor the
document allows is a valid one (a page of the rows below that id). A page never shifts when
rows are added meanwhile.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Protocol, TypeVar

from fastapi import Query
from pydantic import BeforeValidator

from server.api.schemas import MAX_ROW_ID
from server.api.schemas.common import digits_only
from server.store.crud.lists import ListOrder

MAX_PAGE = 100
"""The most items one page holds (a bound on the response's size and the query's cost)."""
DEFAULT_PAGE = 20
"""Items per page when ``limit`` is not given."""

PageLimit = Annotated[
    int,
    Query(ge=1, le=MAX_PAGE, description=f"Items per page (1 to {MAX_PAGE})."),
    BeforeValidator(digits_only),
]
PageCursor = Annotated[
    int | None,
    Query(
        ge=1,
        le=MAX_ROW_ID,
        description="The ``next_cursor`` of the previous page (the page holds the rows below "
        "that id); omit for the first page.",
    ),
    BeforeValidator(digits_only),  # an id, written as path ids are
]

PageOrder = Annotated[
    ListOrder,
    Query(description="``newest`` first (the default) or ``oldest`` first; cursors follow it."),
]


class _Row(Protocol):
    @property
    def id(self) -> int: ...


R = TypeVar("R", bound=_Row)


def page_of(rows: Sequence[R], limit: int) -> tuple[list[R], int | None]:
    """Split ``rows``, fetched with ``limit + 1`` (newest first), into the page and the cursor
    of the next one (None when nothing follows)."""
    items = list(rows[:limit])
    return items, items[-1].id if len(rows) > limit else None
