"""The web view and the API docs, from files shipped in the packages (nothing from a CDN).

``GET /`` and ``/ui/`` answer the web view: one page (``server/ui/index.html``, plain HTML, CSS and
JavaScript modules, no build step) that reads the JSON API and the event streams. ``/docs``
(Swagger UI) and ``/redoc`` load their scripts from ``/ui/vendor/``, the copies that the
``fastapi-offline`` package ships. The page needs no token and puts none in a URL: it only
reads. Its responses carry a strict Content-Security-Policy (scripts, styles and connections
from this origin only, no inline code), so even a string that slipped past the page's escaping
could not run. ``/docs`` and ``/redoc`` get one as strict but for their own inline script (allowed
by its hash) and injected styles; it lets no image come from elsewhere, so ReDoc's footer logo
(a CDN address inside its bundle) is never fetched.
"""

from __future__ import annotations

import base64
import hashlib
import importlib.resources
import re
from pathlib import Path

from fastapi import APIRouter
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, RedirectResponse

from agents.manifest import DECISIONS, ES_NEURONS, INPUTS, JUDGEMENTS, PFC_SOURCES, VERDICTS
from screener.findings import INPUT_WORDS, ROLE
from server.api.errors import api_error, cut
from server.api.files import ServedFile
from studies.registry import KINDS

router = APIRouter(include_in_schema=False)

UI_DIR = Path(__file__).resolve().parent
VENDOR_DIR = Path(str(importlib.resources.files("fastapi_offline") / "static"))
MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".png": "image/png",
}
CONTENT_SECURITY_POLICY = "; ".join(
    (
        "default-src 'none'",
        "script-src 'self'",
        "style-src 'self'",
        "img-src 'self' data:",
        "connect-src 'self'",
        "base-uri 'none'",
        "form-action 'none'",
        "frame-ancestors 'none'",
    )
)
PAGE_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}


INPUT_SYMBOLS = dict(zip(INPUTS, ("p", "l", "w", "g", "st1", "st2", "st3", "f"), strict=True))
"""The paper's short names of the inputs, as the drawing labels them."""
ANATOMY = {
    "inputs": INPUTS,
    "input_words": INPUT_WORDS,
    "input_short": INPUT_SYMBOLS,
    "sensor": ES_NEURONS,
    "decision": DECISIONS,
    "pfc_sources": PFC_SOURCES,
    "judgement": JUDGEMENTS,
    "verdict": VERDICTS,
    "roles": ROLE,
}
"""The negotiator's layers and what each neuron means, for the inspector's drawing (the page
takes them from here, so it names exactly what the manifest and the screener name)."""

RESULTS = {
    name: {"headline": kind.headline, "table": kind.table, "columns": kind.columns}
    for name, kind in KINDS.items()
}
"""How each job kind's result reads (the registry's headline fields, table and columns), so
the job page shows first what the command's summary shows first."""


def _servable(folder: Path) -> dict[str, Path]:
    """The files of ``folder`` that may be served, by name (a fixed list: no path is ever
    built from the request)."""
    return {path.name: path for path in folder.iterdir() if path.suffix in MEDIA_TYPES}


UI_FILES = _servable(UI_DIR)
VENDOR_FILES = _servable(VENDOR_DIR)


def _file(files: dict[str, Path], name: str) -> FileResponse:
    path = files.get(name)
    if path is None:
        raise api_error(404, f"no file {cut(name)!r} here", loc=("path", "name"), kind="not_found")
    return ServedFile(path, media_type=MEDIA_TYPES[path.suffix], headers=PAGE_HEADERS)


@router.get("/")
async def root() -> FileResponse:
    """The web view (the same page as ``/ui/``)."""
    return _file(UI_FILES, "index.html")


@router.get("/ui")
async def ui_folder() -> RedirectResponse:
    return RedirectResponse("/ui/", status_code=307)


@router.get("/ui/")
async def ui_page() -> FileResponse:
    """The page; it routes between its views by the URL's fragment (``#/auctions/3``)."""
    return _file(UI_FILES, "index.html")


@router.get("/ui/vendor/{name}")
async def vendor_file(name: str) -> FileResponse:
    """Swagger UI's and ReDoc's own files."""
    return _file(VENDOR_FILES, name)


@router.get("/ui/neurons.json")
async def anatomy() -> JSONResponse:
    """The negotiator's layers and neuron meanings."""
    return JSONResponse(ANATOMY, headers=PAGE_HEADERS)


@router.get("/ui/kinds.json")
async def result_layouts() -> JSONResponse:
    """How each job kind's result reads."""
    return JSONResponse(RESULTS, headers=PAGE_HEADERS)


@router.get("/ui/{name}")
async def ui_file(name: str) -> FileResponse:
    """A script, style sheet or icon of the page."""
    return _file(UI_FILES, name)


def _page_with_policy(page: HTMLResponse) -> tuple[bytes, dict[str, str]]:
    """A docs page with a policy that runs its own inline script (by hash) and files from
    this origin, and loads nothing from anywhere else: ReDoc's CDN logo is never fetched. Its
    ``<html>`` says the page's language (English), as the web view's does."""
    body = bytes(page.body).replace(b"<html>", b'<html lang="en">', 1)
    hashes = " ".join(
        "'sha256-" + base64.b64encode(hashlib.sha256(script).digest()).decode() + "'"
        for script in re.findall(rb"<script>(.*?)</script>", body, flags=re.S)
    )
    policy = "; ".join(
        (
            "default-src 'none'",
            f"script-src 'self' {hashes}".strip(),
            "style-src 'self' 'unsafe-inline'",  # both inject styles; styles run no code
            "img-src 'self' data:",
            "connect-src 'self'",
            "worker-src blob:",  # ReDoc's search runs in a worker built from a blob
            "base-uri 'none'",
            "form-action 'none'",
            "frame-ancestors 'none'",
        )
    )
    return body, {**PAGE_HEADERS, "Content-Security-Policy": policy}


SWAGGER_PAGE = _page_with_policy(
    get_swagger_ui_html(
        openapi_url="/openapi.json",
        title="srd-auction: API docs",
        swagger_js_url="/ui/vendor/swagger-ui-bundle.js",
        swagger_css_url="/ui/vendor/swagger-ui.css",
        swagger_favicon_url="/ui/vendor/favicon.png",
    )
)
REDOC_PAGE = _page_with_policy(
    get_redoc_html(
        openapi_url="/openapi.json",
        title="srd-auction: API reference",
        redoc_js_url="/ui/vendor/redoc.standalone.js",
        redoc_favicon_url="/ui/vendor/favicon.png",
        with_google_fonts=False,
    )
)


@router.get("/docs")
async def swagger_ui() -> HTMLResponse:
    """Swagger UI over ``/openapi.json``."""
    return HTMLResponse(SWAGGER_PAGE[0], headers=SWAGGER_PAGE[1])


@router.get("/redoc")
async def redoc() -> HTMLResponse:
    """ReDoc over ``/openapi.json``."""
    return HTMLResponse(REDOC_PAGE[0], headers=REDOC_PAGE[1])
