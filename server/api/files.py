"""Files as the API serves them (job artifacts, the web view's files): starlette's
``FileResponse`` plus what RFC 9110 asks of an origin server that sends validators.

* Preconditions (section 13.2) are evaluated before the file is sent: ``If-Match`` (or, without
  it, ``If-Unmodified-Since``) that fails is 412; ``If-None-Match`` (or, without it,
  ``If-Modified-Since``) that matches is 304 for ``GET`` and ``HEAD``, with the 200's headers
  but the body's own (a cache merges them into what it stored: a 304 that lacked a page's own
  Content-Security-Policy got the API's strict one, and the page's scripts stopped).
* A ``Range`` that is malformed, or of a unit other than bytes, is ignored: the whole file, 200
  (section 14.2; starlette answered 400); one the file cannot satisfy is 416.
* Refusals are JSON, as every error of the API is (starlette answers them in plain text).
"""

from __future__ import annotations

import os
import re
from datetime import UTC, datetime
from email.utils import parsedate_to_datetime
from pathlib import Path
from typing import Any

from fastapi.responses import FileResponse
from starlette.datastructures import Headers
from starlette.types import Message, Receive, Scope, Send

from server.api.errors import api_error, problem_response

_RANGE = re.compile(
    r"[ \t]*bytes={r}(?:[ \t]*,[ \t]*{r})*[ \t]*".format(r="(?:[0-9]+-[0-9]*|-[0-9]+)"),
    re.IGNORECASE,
)
"""A ``Range`` of bytes as RFC 9110 (14.1.2) spells it (starlette reads its numbers with
``int``, which took ``1_0`` and ``+1`` for numbers)."""


class ServedFile(FileResponse):
    """A file with its validators (``ETag``, ``Last-Modified``) evaluated against the
    request's preconditions (module docstring)."""

    def __init__(self, path: Path, **options: Any) -> None:
        super().__init__(path, stat_result=os.stat(path), **options)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        asked = Headers(scope=scope)
        status = self._precondition(asked, scope["method"])
        if status == 304:  # the 200's headers but the body's own: a cache merges them in
            skipped = (b"content-length", b"content-type", b"content-disposition")
            raw = [(k, v) for k, v in self.raw_headers if k not in skipped]
            await send({"type": "http.response.start", "status": 304, "headers": raw})
            await send({"type": "http.response.body", "body": b""})
            return
        if status == 412:
            header = "If-Match" if "if-match" in asked else "If-Unmodified-Since"
            message = f"the file does not meet the request's precondition ({header})"
            refusal = api_error(412, message, loc=("header", header), kind="precondition")
            await problem_response(refusal)(scope, receive, send)
            return
        if "range" in asked and _RANGE.fullmatch(asked["range"]) is None:
            scope = _without_range(scope)  # malformed, or a unit it does not know: ignored
        refused: list[Message] = []

        async def sending(message: Message) -> None:
            if message["type"] == "http.response.start" and message["status"] in (400, 416):
                refused.append(message)
            elif not refused:
                await send(message)

        await super().__call__(scope, receive, sending)
        if refused and refused[0]["status"] == 400:  # a malformed Range: ignored
            await super().__call__(_without_range(scope), receive, send)
        elif refused:
            headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in refused[0]["headers"]}
            headers.pop("content-length", None)
            headers.pop("content-type", None)
            message = "the Range cannot be served: the file has fewer bytes"
            refusal = api_error(
                416, message, loc=("header", "Range"), kind="range", headers=headers
            )
            await problem_response(refusal)(scope, receive, send)

    def _precondition(self, asked: Headers, method: str) -> int | None:
        """412, 304, or None (serve) for the request's preconditions, in RFC 9110's order."""
        etag = self.headers["etag"]
        modified = parsedate_to_datetime(self.headers["last-modified"])
        if "if-match" in asked:
            if not _matches(asked["if-match"], etag, weak=False):
                return 412
        elif "if-unmodified-since" in asked:
            since = _date(asked["if-unmodified-since"])
            if since is not None and modified > since:
                return 412
        if "if-none-match" in asked:
            if _matches(asked["if-none-match"], etag, weak=True):
                return 304 if method in ("GET", "HEAD") else 412
        elif "if-modified-since" in asked and method in ("GET", "HEAD"):
            since = _date(asked["if-modified-since"])
            if since is not None and modified <= since:
                return 304
        return None


def _matches(header: str, etag: str, *, weak: bool) -> bool:
    """Whether an ``If-Match`` / ``If-None-Match`` list names ``etag`` (or is ``*``);
    ``weak``: weak comparison (``W/`` prefixes ignored)."""
    if header.strip() == "*":
        return True
    tags = [tag.strip() for tag in header.split(",")]
    if weak:
        return any(tag.removeprefix("W/") == etag.removeprefix("W/") for tag in tags)
    return not etag.startswith("W/") and etag in tags


def _date(value: str) -> datetime | None:
    """An HTTP date in any of RFC 9110's three forms (IMF-fixdate, the obsolete RFC 850 and
    asctime forms), always in UTC; None when it is not one (then the condition is ignored)."""
    try:
        date = parsedate_to_datetime(value)
    except (TypeError, ValueError, OverflowError):  # OverflowError: the year 99999999999
        try:  # RFC 850: "Sunday, 06-Dec-26 08:49:37 GMT"
            date = datetime.strptime(value.strip(), "%A, %d-%b-%y %H:%M:%S GMT")
        except ValueError:
            return None
    # An HTTP date is in GMT whatever it says: asctime and "-0000" read as naive
    return date.replace(tzinfo=UTC) if date.tzinfo is None else date


def _without_range(scope: Scope) -> Scope:
    headers = [(k, v) for k, v in scope["headers"] if k not in (b"range", b"if-range")]
    return {**scope, "headers": headers}
