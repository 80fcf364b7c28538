"""Every request body, checked before any route sees it: its size, its media type, its encoding
and its JSON.

``RequestBodyMiddleware`` reads the body (refusing more than ``max_bytes``, or a route's
``smaller`` bound, with 413, by Content-Length up front and by counting what arrives), then,
for a request that carries one:

* a media type other than JSON (``application/json`` or ``application/*+json``), or a
  compressed body (``Content-Encoding``), gets 415 (a body without a ``Content-Type`` is read
  as JSON);
* bytes that are not UTF-8 (a UTF-16 body, a byte-order mark), text that is not JSON, JSON
  nested deeper than ``MAX_DEPTH``, or holding more than ``MAX_CONTAINERS`` arrays and objects
  or ``MAX_MEMBERS`` object members, get 422 at ``["body"]`` (a malformed body, as FastAPI
  answers invalid JSON);
* a key given twice in one object, or a NaN / Infinity token or a number too big for a float
  (``1e999``), gets 422 naming its path;
* a ``Transfer-Encoding`` other than ``chunked`` (``gzip, chunked``) gets 501 naming it: the
  server does not decode transfer codings, and would read such a body as plain.

The size, the media type and the encoding are judged on the header before the body is read:
a client that sent ``Expect: 100-continue`` is refused without its 100 and sends no body. (A
token is checked after the body: FastAPI reads it before it runs a route's dependencies.)

What passes reaches the route unchanged; the route validates it against its schema (strict
numbers, booleans and integers). All refusals use the common error body of ``server.api.errors``.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

from fastapi.responses import JSONResponse
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.api.errors import error_item

MAX_DEPTH = 32
"""Deepest nesting of arrays and objects accepted (a manifest nests 5 deep)."""
JSON_MEDIA_TYPES = ("application/json",)
"""Media types of a JSON body, besides the ``application/<anything>+json`` family."""
JSON_TYPE = b"application/json"
"""The ``Content-Type`` a body sent without one is given for the routes."""


MAX_CONTAINERS = 2_000
"""Most arrays and objects in one body (a manifest has 37): what bounds the checks' work on a
body that is all brackets, before any of them runs in Python."""

MAX_MEMBERS = 2_000
"""Most object members (key-value pairs) in one body (a manifest has 143): what bounds the
schemas' work on a body of unknown keys, each of which they refuse apart (21,000 of them took
the event loop a third of a second)."""

MAX_CAREFUL_BYTES = 65_536
"""Largest body searched for the place of a key given twice, a NaN, too long an integer or too
deep a nesting (every upload fits): a bigger one is refused at ``["body"]``, saying what."""

MAX_INT_DIGITS = 4300
"""Longest integer read (Python's own bound on reading one): a longer one gets 422 at its path."""


class BodyRefusedError(Exception):
    """The body cannot be accepted: HTTP status, message, location of the problem, kind."""

    def __init__(self, status: int, msg: str, loc: tuple[str | int, ...], kind: str) -> None:
        super().__init__(msg)
        self.status, self.msg, self.loc, self.kind = status, msg, loc, kind


class _Pairs(list[tuple[str, Any]]):
    """A JSON object as parsed: its (key, value) pairs in order, duplicates kept."""


def _resolve(value: Any, path: tuple[str | int, ...], depth: int) -> Any:
    """Turn parsed pairs into dicts, refusing duplicate keys and too deep a nesting (``depth``:
    how many arrays and objects hold ``value``)."""
    if depth >= MAX_DEPTH and isinstance(value, _Pairs | list):
        raise BodyRefusedError(
            422, f"JSON nested deeper than {MAX_DEPTH} levels", ("body",), "json_depth"
        )
    if isinstance(value, _Pairs):
        out: dict[str, Any] = {}
        for key, item in value:
            if _SURROGATE.search(key):
                shown = key.encode("utf-8", "backslashreplace").decode("ascii", "replace")
                raise BodyRefusedError(
                    422,
                    f'key "{shown}" is not text: it holds a lone surrogate escape',
                    ("body", *path),
                    "not_text",
                )
            if key in out:
                raise BodyRefusedError(
                    422, f"key {key!r} appears twice", ("body", *path, key), "duplicate_key"
                )
            out[key] = _resolve(item, (*path, key), depth + 1)
        return out
    if isinstance(value, list):  # plain items as they are: a long list of numbers stays cheap
        for i, item in enumerate(value):
            if isinstance(item, _LOOKED_INTO) or (
                isinstance(item, float) and not math.isfinite(item)
            ):
                value[i] = _resolve(item, (*path, i), depth + 1)
        return value
    if isinstance(value, _LongInt):
        raise BodyRefusedError(
            422,
            f"a number of more than {MAX_INT_DIGITS} digits",
            ("body", *path),
            "number_too_long",
        )
    if isinstance(value, float) and not math.isfinite(value):  # NaN, Infinity, -Infinity
        raise BodyRefusedError(422, "must be a finite number", ("body", *path), "finite_number")
    return value


_LOOKED_INTO = (_Pairs, list, str)
"""What ``_resolve`` is called on within a list (a str: ``_LongInt``), besides non-finite floats."""


class _UnfitError(Exception):
    """The fast pass met a duplicate key, a non-finite number, too long an integer or too deep
    a nesting (the message and kind say which): the careful pass (``_resolve``) says where."""

    def __init__(self, msg: str, kind: str) -> None:
        super().__init__(msg)
        self.msg, self.kind = msg, kind


class _LongInt(str):
    """An integer too long to read, as the careful pass found it (``_resolve`` refuses it)."""


def _too_long(text: str) -> bool:
    return len(text) - text.startswith("-") > MAX_INT_DIGITS


def _int_careful(text: str) -> int | _LongInt:
    return _LongInt(text) if _too_long(text) else int(text)


_DIGITS_AS_ZERO = bytes.maketrans(b"123456789", b"0" * 9)
_LONG_DIGITS = b"0" * (MAX_INT_DIGITS + 1)
"""A run of digits that could be an integer too long to read (or a long string or fraction),
looked for once every digit reads ``0`` (``_DIGITS_AS_ZERO``): only then does a pass read each
integer in Python. A plain substring search: a pattern tried at every place took 10–17 ms on
256 KB of anything, and tried inside runs of digits, 15 ms a KB of them."""
_BIG_NUMBERS = (b"e000", b"E000", b"e+000", b"E+000", b"0" * 309)
"""What a number too big for a float (``1e999``, which JSON's reader makes infinite) needs, in
the same digits-as-zero bytes: an exponent of three digits or more, or 309 digits in a row.
Only a body holding one reads each of its floats in Python (``_finite_float``)."""


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _UnfitError("must be a finite number", "finite_number")
    return value


_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*(?:"|\\?\Z)', re.DOTALL)
"""A JSON string (in UTF-8, whose multi-byte characters hold no quote or backslash byte); one
left open runs to the end of the text (the parser refuses it after), so that no search restarts
inside it: every escaped quote of an open string had restarted a scan to the end (22 KB of them
took 3 s). A backslash escapes any character here, a line break too (``DOTALL``): one that did
not would break a string into restarts again."""
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")


def _brackets(raw: bytes) -> bytes:
    """The brackets of JSON ``raw`` in order, strings left out; refuses more than
    ``MAX_CONTAINERS`` arrays and objects or ``MAX_MEMBERS`` object members (counted at C
    speed, before any Python loop)."""
    outside = _STRING.sub(b"", raw)
    if outside.count(b"[") + outside.count(b"{") > MAX_CONTAINERS:
        raise BodyRefusedError(
            422,
            f"more than {MAX_CONTAINERS} arrays and objects in one body",
            ("body",),
            "json_size",
        )
    if outside.count(b":") > MAX_MEMBERS:  # outside strings, a colon ends an object's key
        raise BodyRefusedError(
            422, f"more than {MAX_MEMBERS} object members in one body", ("body",), "json_size"
        )
    return outside.translate(None, _NOT_BRACKETS)


def _nesting(brackets: bytes) -> int:
    """How deep the arrays and objects nest, from their brackets (``_brackets``)."""
    depth = deepest = 0
    for bracket in brackets:
        if bracket in b"[{":
            depth += 1
            if depth > deepest:
                deepest = depth
        else:
            depth -= 1
    return deepest


def _unique(items: list[tuple[str, Any]]) -> dict[str, Any]:
    out = dict(items)
    if len(out) != len(items):
        raise _UnfitError("a key appears twice in one object", "duplicate_key")
    return out


_SURROGATE = re.compile("[\ud800-\udfff]")
"""A lone surrogate, which only a ``\\uD800``-style escape puts in a JSON string: no text."""


def _unique_text(items: list[tuple[str, Any]]) -> dict[str, Any]:
    """``_unique``, refusing a key that is no text (a lone surrogate escape): one would reach
    the messages that name it, and no text encoding holds it."""
    if any(_SURROGATE.search(key) for key, _ in items):
        raise _UnfitError("a key is not text: it holds a lone surrogate escape", "not_text")
    return _unique(items)


def _non_finite(_: str) -> Any:
    raise _UnfitError("must be a finite number", "finite_number")


def _fast(raw: bytes, text: str) -> Any:
    """The JSON of ``text`` (``raw`` decoded), objects built as they are parsed; raises
    ``_UnfitError`` for anything ``_resolve`` would refuse (without saying where)."""
    brackets = _brackets(raw) if b"[" in raw or b"{" in raw else b""
    digits = raw.translate(_DIGITS_AS_ZERO)
    if _LONG_DIGITS in digits:
        raise _UnfitError(f"a number of more than {MAX_INT_DIGITS} digits", "number_too_long")
    big = any(pattern in digits for pattern in _BIG_NUMBERS)
    escapes = b"\\u" in raw  # only an escape can spell a lone surrogate
    hook = _unique_text if escapes else _unique
    value = json.loads(
        text,
        object_pairs_hook=hook,
        parse_constant=_non_finite,
        parse_float=_finite_float if big else None,
    )
    if _nesting(brackets) > MAX_DEPTH:
        raise _UnfitError(f"JSON nested deeper than {MAX_DEPTH} levels", "json_depth")
    return value


def parse_strict_json(raw: bytes) -> Any:
    """Decode a JSON body strictly (see the module docstring); raises BodyRefusedError."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise BodyRefusedError(
            422, f"the body is not UTF-8 (byte {exc.start})", ("body",), "not_utf8"
        ) from exc
    if text.startswith("\ufeff"):
        raise BodyRefusedError(422, "the body starts with a byte-order mark", ("body",), "bom")
    long_ints = False  # the fast pass looks for them first: only its refusal says they are in
    try:
        return _fast(raw, text)
    except RecursionError:
        pass  # the careful pass below says so
    except _UnfitError as unfit:
        long_ints = unfit.kind == "number_too_long"
        if len(text) > MAX_CAREFUL_BYTES:  # what, but not where: a bounded amount of work
            raise BodyRefusedError(
                422,
                f"{unfit.msg} (in a body over {MAX_CAREFUL_BYTES} bytes)",
                ("body",),
                unfit.kind,
            ) from unfit
    except ValueError as exc:
        raise BodyRefusedError(422, f"the body is not JSON: {exc}", ("body",), "not_json") from exc
    try:
        parsed = json.loads(
            text, object_pairs_hook=_Pairs, parse_int=_int_careful if long_ints else None
        )
    except ValueError as exc:
        raise BodyRefusedError(422, f"the body is not JSON: {exc}", ("body",), "not_json") from exc
    except RecursionError as exc:
        raise BodyRefusedError(
            422, f"JSON nested deeper than {MAX_DEPTH} levels", ("body",), "json_depth"
        ) from exc
    return _resolve(parsed, (), 0)


def _is_json(content_type: str) -> bool:
    media = content_type.split(";", 1)[0].strip().lower()
    return media in JSON_MEDIA_TYPES or (
        media.startswith("application/") and media.endswith("+json")
    )


def _charset_ok(content_type: str) -> bool:
    for parameter in content_type.split(";")[1:]:
        name, _, value = parameter.partition("=")
        if name.strip().lower() == "charset" and value.strip().strip('"').lower() != "utf-8":
            return False
    return True


class RequestBodyMiddleware:
    """Size, media type, encoding and JSON checks of request bodies (module docstring)."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        max_bytes: int,
        smaller: tuple[tuple[str, re.Pattern[str], int, str], ...] = (),
    ) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.smaller = smaller
        """(method, path pattern, bytes, what is refused) of routes that take less."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope["headers"])
        for listed in (b"transfer-encoding", b"content-encoding"):  # given twice: one list, as
            values = [v for k, v in scope["headers"] if k == listed]  # HTTP reads it (RFC 9110)
            if len(values) > 1:
                headers[listed] = b", ".join(values)
        most, too_large = self.max_bytes, f"request body larger than {self.max_bytes} bytes"
        for method, path, bytes_, words in self.smaller:
            if scope["method"] == method and path.fullmatch(scope["path"]) and bytes_ < most:
                most, too_large = bytes_, words
        declared = headers.get(b"content-length")
        if declared is not None and (not declared.isdigit() or int(declared) > most):
            if declared.isdigit():
                error = BodyRefusedError(413, too_large, ("header", "Content-Length"), "body_size")
            else:
                error = BodyRefusedError(
                    400, "Content-Length is not a number", ("header", "Content-Length"), "header"
                )
            await _refuse(send, error)
            return
        content_type = headers.get(b"content-type", b"").decode("latin-1")
        if (coding := headers.get(b"transfer-encoding")) is not None and not _chunked(coding):
            await _refuse(send, BodyRefusedError(501, _UNKNOWN_CODING, _CODING_LOC, "coding"))
            return
        if (declared is not None and int(declared) > 0) or b"transfer-encoding" in headers:
            try:  # a body is coming: refused on its header alone before it is asked for
                # (uvicorn sends ``Expect: 100-continue``'s 100 at the first read)
                _plain(headers.get(b"content-encoding", b"").decode("latin-1"))
                _media_type(content_type)
            except BodyRefusedError as error:
                await _refuse(send, error)
                return
        body = bytearray()
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away
                return
            body += message.get("body", b"")
            if len(body) > most:
                await _refuse(send, BodyRefusedError(413, too_large, ("body",), "body_size"))
                return
            if not message.get("more_body", False):
                break
        if body:
            try:
                _plain(headers.get(b"content-encoding", b"").decode("latin-1"))
                _media_type(content_type)
                parse_strict_json(bytes(body))
            except BodyRefusedError as error:
                if _served(scope):  # else the route's absence is the answer: 404 or 405
                    await _refuse(send, error)
                    return
            if not content_type:  # read as JSON: the routes are told so (an empty header,
                # ``Content-Type;`` in curl, is replaced: the first of two is the one read)
                kept = [(k, v) for k, v in scope["headers"] if k.lower() != b"content-type"]
                scope = {**scope, "headers": [*kept, (b"content-type", JSON_TYPE)]}
        delivered = False

        async def replay() -> Message:
            nonlocal delivered
            if delivered:
                return await receive()
            delivered = True
            return {"type": "http.request", "body": bytes(body), "more_body": False}

        await self.app(scope, replay, send)


def _served(scope: Scope) -> bool:
    """Whether some route serves the request's method at its path (``app.state.routes``, the
    app's flat list of routes): a body sent where none is served is not judged."""
    routes = getattr(scope["app"].state, "routes", ())
    return any(route.matches(scope)[0] == Match.FULL for route in routes)


def _media_type(content_type: str) -> None:
    """A body that is not UTF-8 JSON by its ``Content-Type`` gets 415; a body without one is
    read as JSON (``requests.post(url, data=text)`` sends none)."""
    if content_type and not _is_json(content_type):
        raise BodyRefusedError(
            415,
            f"the body must be JSON (Content-Type: application/json), not {content_type}",
            ("header", "Content-Type"),
            "media_type",
        )
    if not _charset_ok(content_type):
        raise BodyRefusedError(
            415, "the body must be UTF-8 JSON", ("header", "Content-Type"), "charset"
        )


_UNKNOWN_CODING = (
    "the body must be sent as is or chunked: Transfer-Encoding other than chunked "
    "(gzip, deflate, compress) is not implemented"
)
_CODING_LOC = ("header", "Transfer-Encoding")


def _chunked(transfer_encoding: bytes) -> bool:
    """Whether a request's ``Transfer-Encoding`` is plain chunking, the one transfer coding
    read here: a body labelled ``gzip, chunked`` would otherwise be read as plain (RFC 9112,
    section 6.1: 501 for a transfer coding not understood)."""
    codings = [c.strip().lower() for c in transfer_encoding.decode("latin-1").split(",")]
    return codings == ["chunked"]


def _plain(content_encoding: str) -> None:
    """A compressed body (``Content-Encoding: gzip``) gets 415: bodies are read as they come."""
    encoding = content_encoding.strip().lower()
    if any(coding.strip() not in ("", "identity") for coding in encoding.split(",")):
        raise BodyRefusedError(
            415,
            f"the body must be plain JSON, not Content-Encoding: {encoding}",
            ("header", "Content-Encoding"),
            "content_encoding",
        )


async def _refuse(send: Send, error: BodyRefusedError) -> None:
    response = JSONResponse(
        {"detail": [error_item(error.msg, loc=error.loc, kind=error.kind)]},
        status_code=error.status,
        headers={"Connection": "close"},
    )
    await response({"type": "http"}, _no_receive, send)


async def _no_receive() -> Message:
    return {"type": "http.disconnect"}
