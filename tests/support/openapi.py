"""Answers checked against the OpenAPI document the server publishes: every status an answer
has is listed for its operation, with the media type it was sent as."""

from __future__ import annotations

from typing import Any

import httpx


def assert_documented(document: dict[str, Any], route: str, response: httpx.Response) -> None:
    """``response`` (to a request on ``route``, the document's path template) is one its
    operation lists: its status, and, if it has a body, its media type."""
    operation = document["paths"][route][response.request.method.lower()]
    code = str(response.status_code)
    assert code in operation["responses"], f"{route} answered {code}, not in its document"
    if response.content:
        media = response.headers["content-type"].split(";")[0].strip()
        listed = operation["responses"][code].get("content", {})
        assert media in listed, f"{route}'s {code} was {media}; its document says {list(listed)}"
