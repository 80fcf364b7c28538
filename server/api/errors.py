"""One error body for every 4xx/5xx: ``{"detail": [{"loc": [...], "msg": ..., "type": ...}]}``.

It is the shape of FastAPI's own 422, so clients parse a single format; ``loc`` names the field
(``["body", "external_sensor", "PG", "bias"]``), the header, or the path parameter at fault.
The services and the routes refuse a request by raising a ``RequestError`` (``api_error``,
``validation_error``); the framework's own errors get the same body.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any, cast

from fastapi import FastAPI, Request, WebSocket
from fastapi.exceptions import RequestValidationError, WebSocketRequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from sqlalchemy.exc import DBAPIError
from sqlalchemy.exc import TimeoutError as PoolTimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import HTTPConnection
from starlette.routing import Match
from starlette.types import ExceptionHandler
from starlette.websockets import WebSocketState

from agents.manifest import without_tags
from server.store.db import (
    DATABASE_RETRY_AFTER_S,
    DatabaseUnavailableError,
    answer_of_outage,
    is_database_outage,
)

TRY_AGAIN_LATER = 1013
"""The WebSocket close code of a socket whose database went away while it was open."""


class ErrorItem(BaseModel):
    """One problem: where (``loc``), what (``msg``), and a machine-readable ``type``."""

    loc: list[str | int]
    msg: str
    type: str


class ErrorBody(BaseModel):
    """Every error response."""

    detail: list[ErrorItem]


MAX_DETAIL = 20
"""Problems listed in one error body at most: past it, one last entry counts the rest (a body of
thousands of bad items would otherwise be answered with megabytes)."""


def error_item(msg: str, *, loc: Sequence[str | int] = (), kind: str = "error") -> dict[str, Any]:
    """A ``detail`` entry (each ``loc`` key cut to ``MAX_LOC_PART`` characters)."""
    return {
        "loc": [cut(part) if isinstance(part, str) else part for part in loc],
        "msg": msg,
        "type": kind,
    }


def cut(name: str) -> str:
    """A name from the request as an answer shows it: its first ``MAX_LOC_PART`` characters
    (a key of 200,000 characters is named by its start)."""
    return name if len(name) <= MAX_LOC_PART else name[:MAX_LOC_PART] + "…"


def capped(items: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """The first ``MAX_DETAIL`` entries, then one that counts the others (at the first
    left out's place)."""
    listed = list(items)
    if len(listed) <= MAX_DETAIL:
        return listed
    rest = len(listed) - MAX_DETAIL
    more = error_item(
        f"and {rest} more problems, not listed (the first {MAX_DETAIL} are; the next is at "
        f"{'.'.join(str(part) for part in listed[MAX_DETAIL]['loc'])})",
        loc=tuple(listed[MAX_DETAIL]["loc"][:1]),  # where they are: the body, the query...
        kind="more_problems",
    )
    return [*listed[:MAX_DETAIL], more]


class RequestError(Exception):
    """A request the service layer refuses: the HTTP status of its sort of problem and the
    ``detail`` entries saying what and where (the app answers it with the common body)."""

    def __init__(
        self,
        status: int,
        items: Iterable[dict[str, Any]],
        *,
        headers: Mapping[str, str] | None = None,
    ) -> None:
        self.status = status
        self.items = capped(items)
        self.headers = dict(headers or {})
        super().__init__("; ".join(str(item["msg"]) for item in self.items))


def api_error(
    status: int,
    msg: str,
    *,
    loc: Sequence[str | int] = (),
    kind: str = "error",
    headers: Mapping[str, str] | None = None,
) -> RequestError:
    """A RequestError with one ``detail`` entry (raise it)."""
    return RequestError(status, [error_item(msg, loc=loc, kind=kind)], headers=headers)


def validation_error(items: Iterable[dict[str, Any]]) -> RequestError:
    """A 422 with several ``detail`` entries."""
    return RequestError(422, items)


MAX_LOC_PART = 64
"""Characters of one ``loc`` part at most (a key of 200,000 characters is named by its start)."""


def _json_safe_loc(loc: Iterable[Any]) -> list[str | int]:
    """A path into the request as the answer names it: pydantic's union tags left out, each
    key cut to ``MAX_LOC_PART`` characters."""
    parts = [part if isinstance(part, int) else str(part) for part in loc]
    return [part if isinstance(part, int) else cut(part) for part in without_tags(parts)]


def allowed_methods(request: Request) -> list[str]:
    """Every method some route serves at the request's path (a 405 names them all; Starlette
    names only those of the first route whose path matches). ``app.state.routes`` is the flat
    list of the app's routes (``create_app`` keeps it). ``HEAD`` wherever ``GET`` is
    (``server.api.hardening`` answers it)."""
    methods: set[str] = set()
    for route in request.app.state.routes:
        match, _ = route.matches({**request.scope, "method": "GET"})
        if match != Match.NONE:
            methods |= getattr(route, "methods", None) or set()
    if "GET" in methods:
        methods.add("HEAD")
    return sorted(methods)


async def _http_exception(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    detail: Any = exc.detail
    headers = dict(exc.headers or {})
    if exc.status_code == 405:
        allowed = ", ".join(allowed_methods(request))
        headers["Allow"] = allowed
        detail = [
            error_item(
                f"{request.method} is not served at this path, which serves {allowed}",
                loc=("method",),
                kind="method_not_allowed",
            )
        ]
    elif not isinstance(detail, list):  # framework errors (404 route) carry a string
        detail = [error_item(str(detail), loc=("path",), kind="http_error")]
    return JSONResponse({"detail": detail}, status_code=exc.status_code, headers=headers)


def _validation_detail(exc: RequestValidationError | WebSocketRequestValidationError) -> list[Any]:
    """The framework's errors, each once (a parameter that two dependencies declare is
    checked, and refused, twice); told apart by their whole path, so that two long keys that
    begin alike, shown cut, are two problems."""
    items: dict[tuple[Any, ...], dict[str, Any]] = {}
    for err in exc.errors():
        loc = tuple(err.get("loc", ()))
        item = error_item(
            str(err.get("msg", "invalid")),
            loc=_json_safe_loc(loc),
            kind=str(err.get("type", "value_error")),
        )
        items.setdefault((tuple(map(str, loc)), item["msg"], item["type"]), item)
    return capped(items.values())


async def _request_validation(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    return JSONResponse({"detail": _validation_detail(exc)}, status_code=422)


async def _socket_validation(websocket: WebSocket, exc: Exception) -> None:
    """A WebSocket handshake whose path does not validate: 422 naming the parameter (instead
    of the framework's bare close)."""
    assert isinstance(exc, WebSocketRequestValidationError)
    await websocket.send_denial_response(
        JSONResponse({"detail": _validation_detail(exc)}, status_code=422)
    )


def problem_response(exc: RequestError) -> JSONResponse:
    """The common body and headers of a refusal (a 401 names the Bearer scheme), for a request
    or a refused WebSocket handshake."""
    headers = dict(exc.headers)
    if exc.status == 401:
        headers.setdefault("WWW-Authenticate", "Bearer")
    return JSONResponse({"detail": exc.items}, status_code=exc.status, headers=headers)


async def _problem(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestError)
    return problem_response(exc)


def database_unavailable(cause: BaseException | str) -> RequestError:
    """The 503 of a request the database cannot serve now (``cause``: the error met, or what
    to say), with when to try again."""
    if isinstance(cause, BaseException):
        unreachable = isinstance(cause, DatabaseUnavailableError)
        cause = str(cause) if unreachable else answer_of_outage(cause)
    return api_error(
        503,
        cause,
        loc=("database",),
        kind="db_unavailable",
        headers={"Retry-After": str(DATABASE_RETRY_AFTER_S)},
    )


async def _database_unavailable(connection: HTTPConnection, exc: Exception) -> JSONResponse | None:
    """A request (or WebSocket handshake) that met a database outage: 503, not a plain 500. A
    statement's own error (a constraint, a bug) is no outage: it goes on to the 500 handler."""
    if not is_database_outage(exc):
        raise exc
    response = problem_response(database_unavailable(exc))
    if not isinstance(connection, WebSocket):
        return response
    if connection.application_state == WebSocketState.CONNECTING:
        await connection.send_denial_response(response)
    else:
        await connection.close(code=TRY_AGAIN_LATER, reason="the database is unavailable")
    return None


async def _internal(request: Request, exc: Exception) -> JSONResponse:
    """Anything no other handler took: a 500 in the common body (the error is logged with its
    traceback by the server, never sent), with the security headers: it is answered outside
    the middleware that adds them."""
    from server.api.hardening import SECURITY_HEADERS  # which imports this module

    return JSONResponse(
        {
            "detail": [
                error_item(
                    "the server met an unexpected error; it is logged. Retry, or report it",
                    loc=("server",),
                    kind="internal_error",
                )
            ]
        },
        status_code=500,
        headers=SECURITY_HEADERS,
    )


def install_error_handlers(app: FastAPI) -> None:
    """Route every framework error through the common body."""
    app.add_exception_handler(Exception, _internal)
    app.add_exception_handler(StarletteHTTPException, _http_exception)
    app.add_exception_handler(RequestValidationError, _request_validation)
    app.add_exception_handler(WebSocketRequestValidationError, _socket_validation)
    app.add_exception_handler(RequestError, _problem)
    # One handler for both scopes: Starlette passes a Request or a WebSocket.
    outage_handler = cast(ExceptionHandler, _database_unavailable)
    for outage in (DatabaseUnavailableError, DBAPIError, PoolTimeoutError):
        app.add_exception_handler(outage, outage_handler)


def link(operation_id: str, parameter: str, field: str) -> dict[str, Any]:
    """An OpenAPI link: feed ``field`` of this response to ``parameter`` of ``operation_id``."""
    return {"operationId": operation_id, "parameters": {parameter: f"$response.body#/{field}"}}


def responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for the error codes a route can answer."""
    text = {
        400: "Unreadable request (bad Content-Length, a token in the query)",
        401: "No bearer token",
        403: "Wrong bearer token",
        404: "No such resource",
        409: "Conflicts with the resource's current state",
        410: "Gone: the fine-tuning round named has closed (or its deadline passed)",
        412: "A precondition failed (If-Match)",
        413: "Request body too large",
        414: "The query is too long",
        415: "Request body is not JSON (Content-Type)",
        416: "The Range asked for cannot be served",
        422: "Invalid input (a body not UTF-8, not JSON or nested too deep among it); ``loc`` "
        "names the field",
        429: "Over a quota or rate limit; ``Retry-After`` says when to try again",
        503: "A service the request needs is unavailable; retry",
        505: "An event stream asked for over HTTP/1.0 (it is sent in chunks: use HTTP/1.1)",
    }
    return {code: {"model": ErrorBody, "description": text[code]} for code in codes}
