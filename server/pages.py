"""Pagination of the lists: the ``limit`` and ``cursor`` query parameters and the cursor format.

A cursor is opaque to clients: URL-safe base64 of ``<resource>:<last id of the page>``. The list
continues below that id (lists are newest first and ids only grow), so a page never shifts when
rows are added meanwhile, and a cursor from one list is refused by another.
"""

from __future__ import annotations

import base64
import binascii
from collections.abc import Sequence
from typing import Annotated, Protocol, TypeVar

from fastapi import Query

from server.errors import api_error
from server.schemas import MAX_ROW_ID

MAX_PAGE = 100
"""The most items one page holds (a bound on the response's size and the query's cost)."""
DEFAULT_PAGE = 20
"""Items per page when ``limit`` is not given."""
MAX_CURSOR_CHARS = 64

PageLimit = Annotated[
    int, Query(ge=1, le=MAX_PAGE, description=f"Items per page (1 to {MAX_PAGE}).")
]
PageCursor = Annotated[
    str | None,
    Query(
        min_length=1,
        max_length=MAX_CURSOR_CHARS,
        description="The ``next_cursor`` of the previous page; omit for the first page.",
    ),
]


def encode_cursor(resource: str, last_id: int) -> str:
    """The cursor that continues ``resource``'s list after the row ``last_id``."""
    return base64.urlsafe_b64encode(f"{resource}:{last_id}".encode()).decode().rstrip("=")


def decode_cursor(resource: str, cursor: str | None) -> int | None:
    """The id a ``resource`` page continues below (None for the first page); 422 naming
    ``cursor`` when it is not a cursor of this list."""
    if cursor is None:
        return None
    try:
        text = base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)).decode("ascii")
    except (binascii.Error, UnicodeDecodeError, ValueError):
        text = ""
    prefix, _, digits = text.partition(":")
    if prefix != resource or not digits.isdigit() or not 1 <= int(digits) <= MAX_ROW_ID:
        raise api_error(
            422,
            f"not a cursor of the {resource} list: pass the next_cursor of its previous page",
            loc=("query", "cursor"),
            kind="bad_cursor",
        )
    return int(digits)


class _Row(Protocol):
    @property
    def id(self) -> int: ...


R = TypeVar("R", bound=_Row)


def page_of(resource: str, rows: Sequence[R], limit: int) -> tuple[list[R], str | None]:
    """Split ``rows``, fetched with ``limit + 1`` (newest first), into the page and the cursor
    of the next one (None when nothing follows)."""
    items = list(rows[:limit])
    more = len(rows) > limit
    return items, encode_cursor(resource, items[-1].id) if more else None
