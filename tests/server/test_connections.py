"""Connection hygiene of a real ``srd serve``: one address holds at most its share of open
connections (others are still served, a trusted proxy is not counted), a header over the size
cap is refused however it arrives, and the protocol's own refusals carry the common JSON error
body.

Clients bind distinct loopback addresses (Linux routes all of 127/8 to the loopback).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from server.cli.launch import ServerProcess
from tests.support.server import ADMIN, module_server

SHARE = 8
HOARDER = "127.0.0.11"
NEIGHBOUR = "127.0.0.12"
PROXY = "127.0.0.13"
MAX_HEADER_BYTES = 16_384
BODY_TIMEOUT_S = 3
SEND_TIMEOUT_S = 2
STREAMS = 2


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    env = {
        "SRD_MAX_CONNECTIONS_PER_ADDRESS": str(SHARE),
        "SRD_MAX_HEADER_BYTES": str(MAX_HEADER_BYTES),
        "SRD_TRUSTED_PROXIES": PROXY,
        "SRD_BODY_TIMEOUT_S": str(BODY_TIMEOUT_S),
        "SRD_SEND_TIMEOUT_S": str(SEND_TIMEOUT_S),
        "SRD_LIMIT_CLIENT_STREAMS": str(STREAMS),
    }
    yield from module_server(tmp_path_factory, "connections", env)


async def _open(server: ServerProcess, address: str) -> tuple[Any, Any]:
    return await asyncio.open_connection("127.0.0.1", server.port, local_addr=(address, 0))


async def _exchange(
    server: ServerProcess, address: str, raw: bytes
) -> tuple[int, dict[str, str], bytes]:
    """Send ``raw`` on a new connection and read the answer until the server closes it."""
    reader, writer = await _open(server, address)
    try:
        writer.write(raw)
        answer = await asyncio.wait_for(reader.read(), 10)
    finally:
        writer.close()
    head, _, body = answer.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    headers = dict(line.lower().split(": ", 1) for line in lines[1:])
    return int(lines[0].split()[1]), headers, body


def _get(path: str, *extra: str) -> bytes:
    lines = [f"GET {path} HTTP/1.1", "Host: test", "Connection: close", *extra]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def _detail(body: bytes) -> dict[str, Any]:
    detail = json.loads(body)["detail"]
    assert len(detail) == 1
    return dict(detail[0])


async def _half_send(
    server: ServerProcess, address: str, count: int, into: list[tuple[Any, Any]]
) -> None:
    """Open ``count`` connections from ``address``, each a request whose header never ends."""
    for _ in range(count):
        reader, writer = await _open(server, address)
        writer.write(b"GET /healthz HTTP/1.1\r\nHost: test\r\n")
        into.append((reader, writer))


async def _hoard(server: ServerProcess) -> dict[str, Any]:
    half_sent: list[tuple[Any, Any]] = []
    try:
        await _half_send(server, HOARDER, SHARE, half_sent)  # the hoarder's share
        await asyncio.sleep(0.2)
        over = await _exchange(server, HOARDER, _get("/healthz"))
        neighbour = await _exchange(server, NEIGHBOUR, _get("/healthz"))
        proxied = await asyncio.gather(
            *(_exchange(server, PROXY, _get("/healthz")) for _ in range(SHARE + 2))
        )
        half_sent.pop()[1].close()  # one of the hoarder's connections ends: its place is free
        await asyncio.sleep(0.2)
        freed = await _exchange(server, HOARDER, _get("/healthz"))
        return {"over": over, "neighbour": neighbour, "proxied": proxied, "freed": freed}
    finally:
        for _, writer in half_sent:
            writer.close()


def test_an_address_holds_its_share_of_connections_and_no_more(server: ServerProcess) -> None:
    result = asyncio.run(_hoard(server))
    status, headers, body = result["over"]
    assert status == 429
    assert headers["content-type"] == "application/json"
    assert int(headers["retry-after"]) >= 1
    item = _detail(body)
    assert item["type"] == "too_many_connections" and item["loc"] == ["connection"]
    assert result["neighbour"][0] == 200  # another address is served meanwhile
    assert [status for status, _, _ in result["proxied"]] == [200] * (SHARE + 2)  # not counted
    assert result["freed"][0] == 200


def test_a_header_over_the_cap_is_refused_whole_or_in_pieces(server: ServerProcess) -> None:
    padding = "X-Padding: " + "a" * (MAX_HEADER_BYTES + 100)
    status, headers, body = asyncio.run(_exchange(server, NEIGHBOUR, _get("/healthz", padding)))
    assert status == 431 and headers["content-type"] == "application/json"
    assert _detail(body)["type"] == "header_too_large"

    async def in_pieces() -> tuple[int, bytes]:
        reader, writer = await _open(server, NEIGHBOUR)
        raw = _get("/healthz", padding)
        try:
            for start in range(0, len(raw), 4096):
                writer.write(raw[start : start + 4096])
                await writer.drain()
            answer = await asyncio.wait_for(reader.read(), 10)
        finally:
            writer.close()
        return int(answer.split()[1]), answer

    status, _ = asyncio.run(in_pieces())
    assert status == 431

    async def behind_a_small_one() -> bytes:
        """A small request, then in the same write one whose header is over the cap: the read
        that ends the first header carries the second whole (it had been answered 200)."""
        reader, writer = await _open(server, NEIGHBOUR)
        try:
            first = b"GET /healthz HTTP/1.1\r\nHost: test\r\n\r\n"  # kept alive
            writer.write(first + _get("/healthz", padding))
            await writer.drain()
            return await asyncio.wait_for(reader.read(), 10)
        finally:
            writer.close()

    answers = asyncio.run(behind_a_small_one())
    assert answers.startswith(b"HTTP/1.1 200") and answers.count(b"HTTP/1.1 ") == 2, answers[:300]
    assert b"HTTP/1.1 431" in answers
    within = "X-Padding: " + "a" * (MAX_HEADER_BYTES // 2)
    assert asyncio.run(_exchange(server, NEIGHBOUR, _get("/healthz", within)))[0] == 200


def test_an_unreadable_request_gets_the_common_error_body(server: ServerProcess) -> None:
    raw = b"POST /submit HTTP/1.1\r\nHost: test\r\nContent-Length: abc\r\n\r\n{}"
    status, headers, body = asyncio.run(_exchange(server, NEIGHBOUR, raw))
    assert status == 400 and headers["content-type"] == "application/json"
    item = _detail(body)
    assert item["type"] == "bad_request" and item["loc"] == ["connection"]


@pytest.mark.parametrize(
    ("head", "status", "kind"),
    [
        ("GET /healthz HTTP/1.1\r\nConnection: close", 400, "bad_host"),
        ("GET /healthz HTTP/1.1\r\nHost: a\r\nHost: b\r\nConnection: close", 400, "bad_host"),
        ("GET /healthz HTTP/2.0\r\nHost: a\r\nConnection: close", 505, "http_version"),
        ("get /healthz HTTP/1.1\r\nHost: a\r\nConnection: close", 501, "unknown_method"),
        ("BREW /healthz HTTP/1.1\r\nHost: a\r\nConnection: close", 501, "unknown_method"),
        # a transfer coding the server does not decode: the body would be read as plain
        (
            "POST /submit HTTP/1.1\r\nHost: a\r\nContent-Type: application/json\r\n"
            "Transfer-Encoding: gzip, chunked\r\nConnection: close\r\n\r\n2\r\n{}\r\n0",
            501,
            "coding",
        ),
        (  # the same list over two header lines
            "POST /submit HTTP/1.1\r\nHost: a\r\nContent-Type: application/json\r\n"
            "Transfer-Encoding: gzip\r\nTransfer-Encoding: chunked\r\nConnection: close\r\n"
            "\r\n2\r\n{}\r\n0",
            501,
            "coding",
        ),
        (
            "POST /submit HTTP/1.1\r\nHost: a\r\nContent-Type: application/json\r\n"
            "Content-Encoding: gzip\r\nContent-Encoding: identity\r\nContent-Length: 2\r\n"
            "Connection: close\r\n\r\n{}",
            415,
            "content_encoding",
        ),
    ],
)
def test_a_header_the_server_will_not_serve_is_refused_before_any_route(
    server: ServerProcess, head: str, status: int, kind: str
) -> None:
    got, headers, body = asyncio.run(_exchange(server, NEIGHBOUR, f"{head}\r\n\r\n".encode()))
    assert (got, headers["content-type"], _detail(body)["type"]) == (
        status,
        "application/json",
        kind,
    )
    # refused below the app, with the headers every answer carries
    assert headers["x-content-type-options"] == "nosniff" and headers["x-frame-options"] == "deny"
    assert headers["content-security-policy"].startswith("default-src 'none'")
    # HTTP/1.0 predates Host: served without one
    raw = b"GET /healthz HTTP/1.0\r\n\r\n"
    assert asyncio.run(_exchange(server, NEIGHBOUR, raw))[0] == 200


KEY = "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ=="


@pytest.mark.parametrize(
    ("lines", "status", "header"),
    [
        ([KEY, "Sec-WebSocket-Version: 8"], 426, "Sec-WebSocket-Version"),
        ([KEY], 400, "Sec-WebSocket-Version"),
        (["Sec-WebSocket-Key: short", "Sec-WebSocket-Version: 13"], 400, "Sec-WebSocket-Key"),
        (["Sec-WebSocket-Version: 13"], 400, "Sec-WebSocket-Key"),
        (
            [f"Sec-WebSocket-Key: {'b' * 6000}", "Sec-WebSocket-Version: 13"],
            400,
            "Sec-WebSocket-Key",
        ),
    ],
)
def test_a_websocket_handshake_the_protocol_refuses_gets_the_common_error_body(
    server: ServerProcess, lines: list[str], status: int, header: str
) -> None:
    """A handshake refused below the app (RFC 6455's own rules) is answered as every refusal
    is: JSON naming the header, the security headers; a version this server does not speak
    with the one it does (RFC 6455, 4.2.2). The library's plain text had none of these."""
    head = [
        "GET /auctions/1/rounds/socket HTTP/1.1",
        "Host: test",
        "Upgrade: websocket",
        "Connection: Upgrade",
        *lines,
    ]
    raw = ("\r\n".join(head) + "\r\n\r\n").encode()
    got, headers, body = asyncio.run(_exchange(server, NEIGHBOUR, raw))
    assert got == status and headers["content-type"] == "application/json"
    item = _detail(body)
    assert item["loc"] == ["header", header] and item["type"] == "handshake", item
    assert len(item["msg"]) <= 161, item  # not the peer's 6,000 bytes said back
    assert header in item["msg"]
    assert headers["x-content-type-options"] == "nosniff"
    assert headers["content-security-policy"].startswith("default-src 'none'")
    if header == "Sec-WebSocket-Version":
        assert headers["sec-websocket-version"] == "13"
    if status == 426:
        assert headers["upgrade"] == "websocket"


def test_a_body_refused_by_its_header_is_not_asked_for(server: ServerProcess) -> None:
    """``Expect: 100-continue``: a media type or an encoding the server refuses is answered
    with the refusal, not with 100 Continue, and the client need not send its body."""

    async def ask(content_type: str, encoding: str = "identity") -> bytes:
        reader, writer = await _open(server, NEIGHBOUR)
        try:
            writer.write(
                (
                    "POST /submit HTTP/1.1\r\nHost: t\r\nExpect: 100-continue\r\n"
                    f"Content-Type: {content_type}\r\nContent-Encoding: {encoding}\r\n"
                    "Content-Length: 20\r\n\r\n"
                ).encode()
            )
            return await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 10)
        finally:
            writer.close()

    for content_type, encoding in (("text/plain", "identity"), ("application/json", "gzip")):
        first = asyncio.run(ask(content_type, encoding))
        assert first.startswith(b"HTTP/1.1 415"), first
    assert asyncio.run(ask("application/json")).startswith(b"HTTP/1.1 100 Continue")


def test_a_body_that_does_not_arrive_in_time_gets_408(server: ServerProcess) -> None:
    """A body still arriving at its deadline (a slow sender, by length or chunked) is answered
    408 with the common body, and the connection closes; before, it closed without a word."""

    async def drip(head: str, part: bytes) -> tuple[bytes, float]:
        reader, writer = await _open(server, NEIGHBOUR)
        try:
            started = time.monotonic()
            writer.write(head.encode() + part)
            answer = await asyncio.wait_for(reader.read(), 30)
            return answer, time.monotonic() - started
        finally:
            writer.close()

    post = "POST /submit HTTP/1.1\r\nHost: t\r\nContent-Type: application/json\r\n"
    for head, part in (
        (post + "Content-Length: 200\r\n\r\n", b'{"participant": '),
        (post + "Transfer-Encoding: chunked\r\n\r\n", b'5\r\n{"a":\r\n'),
    ):
        answer, took = asyncio.run(drip(head, part))
        assert answer.startswith(b"HTTP/1.1 408"), answer
        item = _detail(answer.partition(b"\r\n\r\n")[2])
        assert item["type"] == "body_timeout" and item["loc"] == ["connection"]
        assert BODY_TIMEOUT_S - 0.5 < took < BODY_TIMEOUT_S + 20, took


def test_a_peer_that_reads_none_of_its_answers_is_disconnected(server: ServerProcess) -> None:
    """Three pipelined GETs of a 1.5 MB script on a connection whose peer never reads: the
    server's send buffer fills and stays full. Past SRD_SEND_TIMEOUT_S the connection ends (it
    had been held for ever, a file and megabytes of kernel memory with it)."""
    size = len(httpx.get(f"{server.url}/ui/vendor/swagger-ui-bundle.js", timeout=30).content)
    request = b"GET /ui/vendor/swagger-ui-bundle.js HTTP/1.1\r\nHost: test\r\n\r\n"
    with socket.socket() as peer:
        peer.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
        peer.bind(("127.0.0.14", 0))
        peer.connect(("127.0.0.1", server.port))
        peer.sendall(request * 3)
        time.sleep(SEND_TIMEOUT_S + 2)  # reading nothing
        peer.settimeout(10)
        received = 0
        with contextlib.suppress(ConnectionResetError):
            while chunk := peer.recv(1 << 16):
                received += len(chunk)
    assert received < 3 * size  # ended before its answers were sent (else they all come)


def test_a_stream_with_a_request_pipelined_behind_it_ends_when_its_client_leaves(
    server: ServerProcess,
) -> None:
    """An event stream with a request pipelined behind it on its connection: once its client
    leaves, its place is free at once (uvicorn had told only the request behind it, so the
    stream held its client's share until a keep-alive write failed, and logged a traceback)."""
    created = httpx.post(
        f"{server.url}/auctions", json={"n_fish": 1, "enrollment_s": 3000}, headers=ADMIN
    )
    path = f"/auctions/{created.json()['auction_id']}/events"
    stream = f"GET {path} HTTP/1.1\r\nHost: test\r\n\r\n".encode()
    behind = b"GET /healthz HTTP/1.1\r\nHost: test\r\n\r\n"
    before = server.log_path.read_text().count("Exception in ASGI application")
    peers = []
    for _ in range(STREAMS):  # the address's whole share, each with a request behind it
        peer = socket.create_connection(
            ("127.0.0.1", server.port), source_address=("127.0.0.15", 0)
        )
        peer.sendall(stream + behind)
        peer.settimeout(10)
        assert peer.recv(4096).startswith(b"HTTP/1.1 200"), "the stream did not open"
        peers.append(peer)
    for peer in peers:
        peer.close()
    time.sleep(0.5)
    transport = httpx.HTTPTransport(local_address="127.0.0.15")
    with (
        httpx.Client(transport=transport) as client,
        client.stream("GET", f"{server.url}{path}", timeout=10) as again,
    ):
        assert again.status_code == 200  # its share is free again (429 had held 15 s)
    time.sleep(0.5)
    assert server.log_path.read_text().count("Exception in ASGI application") == before


def test_a_chunked_body_is_bounded_by_its_framing_and_its_trailer(server: ServerProcess) -> None:
    """The app bounds a body's payload; its chunked framing is the protocol's. A trailer over
    the header's cap had never been answered (the app waited for a body the refusal had cut
    off); 12,000 header lines, 1.4 GB of chunk extensions or 250,000 one-byte chunks each held
    the event loop. Each is refused, and the connection closes; a body in a few chunks with a
    small trailer is read as before."""
    post = (
        b"POST /submit HTTP/1.1\r\nHost: t\r\nContent-Type: application/json\r\n"
        b"Transfer-Encoding: chunked\r\nConnection: close\r\n\r\n"
    )
    body = b'{"participant": "chunky"}'

    def chunked(*parts: bytes, trailer: bytes = b"", extension: bytes = b"") -> bytes:
        chunks = b"".join(b"%x%s\r\n%s\r\n" % (len(p), extension, p) for p in parts)
        return post + chunks + b"0\r\n" + trailer + b"\r\n"

    status, _, answer = asyncio.run(_exchange(server, NEIGHBOUR, chunked(body[:9], body[9:])))
    assert status == 422 and '"pfc"' in answer.decode(), answer  # read: the manifest is missing
    small = b"X-Sum: 1\r\n"
    assert asyncio.run(_exchange(server, NEIGHBOUR, chunked(body, trailer=small)))[0] == 422
    cases = {
        "a trailer over the header's cap": (
            chunked(body, trailer=b"X-Pad: " + b"a" * (MAX_HEADER_BYTES + 100) + b"\r\n"),
            431, "header_too_large",
        ),
        "a trailer of too many lines": (chunked(body, trailer=small * 101),
                                        431, "header_too_large"),
        "a header of too many lines": (
            post.replace(b"\r\n\r\n", b"\r\n" + b"X-A: 1\r\n" * 101 + b"\r\n"),
            431, "header_too_large",
        ),
        "one-byte chunks": (chunked(*[body[i : i + 1] for i in range(len(body))] * 50),
                            400, "too_many_chunks"),
        "long chunk extensions": (chunked(body, extension=b";x=" + b"y" * 600_000),
                                  413, "body_size"),
    }  # fmt: skip
    for case, (raw, wanted, kind) in cases.items():
        started = time.monotonic()
        status, headers, answer = asyncio.run(_exchange(server, NEIGHBOUR, raw))
        assert status == wanted, (case, answer)
        assert _detail(answer)["type"] == kind, (case, answer)
        assert headers["connection"] == "close", case
        assert time.monotonic() - started < 5, case


def test_empty_lines_between_requests_count_as_header(server: ServerProcess) -> None:
    """Empty lines before a request line (RFC 9112, 2.2) are header bytes under the header's
    deadline and cap: a connection that sent only line breaks after its first answer had been
    read for ever (2 GB in 3 s, a core) and never closed."""

    async def after_one(tail: bytes) -> bytes:
        """A request, its answer read, then ``tail``: what comes back until the close."""
        reader, writer = await _open(server, NEIGHBOUR)
        try:
            writer.write(b"GET /livez HTTP/1.1\r\nHost: t\r\n\r\n")
            first = await asyncio.wait_for(reader.readuntil(b'{"status":"ok"}'), 10)
            writer.write(tail)
            return first + await asyncio.wait_for(reader.read(-1), 10)
        finally:
            writer.close()

    flooded = asyncio.run(after_one(b"\r\n" * MAX_HEADER_BYTES))
    assert flooded.startswith(b"HTTP/1.1 200") and b"HTTP/1.1 431" in flooded, flooded[-300:]
    then = b"\r\n\r\nGET /livez HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n"
    assert asyncio.run(after_one(then)).count(b"HTTP/1.1 200") == 2


def test_a_request_asking_an_upgrade_with_a_body_is_refused(server: ServerProcess) -> None:
    """The parser stops at an upgrading request's header: a body behind a declined upgrade was
    read as a request of its own, which a client behind a trusted proxy could address as
    anyone. A GET asking to upgrade with a body is 400 and the connection closes."""
    smuggled = b"GET /livez?smuggled=1 HTTP/1.1\r\nHost: t\r\n\r\n"
    raw = (
        b"GET /livez HTTP/1.1\r\nHost: t\r\nConnection: Upgrade\r\nUpgrade: h2c\r\n"
        b"Content-Length: %d\r\n\r\n" % len(smuggled)
    ) + smuggled
    status, _, body = asyncio.run(_exchange(server, NEIGHBOUR, raw))
    assert status == 400 and _detail(body)["type"] == "bad_upgrade"
    time.sleep(0.3)
    assert "smuggled" not in server.log_path.read_text()


@pytest.fixture(scope="module")
def small_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    env = {"SRD_MAX_CONNECTIONS": "16", "SRD_MAX_CONNECTIONS_PER_ADDRESS": str(SHARE)}
    yield from module_server(tmp_path_factory, "small", env)


async def _fill(server: ServerProcess) -> dict[str, Any]:
    half_sent: list[tuple[Any, Any]] = []
    try:  # 15 held (the proxy's are not counted per address): the 16th is one too many
        await _half_send(server, HOARDER, SHARE, half_sent)
        await _half_send(server, PROXY, SHARE - 1, half_sent)
        await asyncio.sleep(0.2)
        full = await _exchange(server, NEIGHBOUR, _get("/healthz"))
        half_sent.pop()[1].close()
        await asyncio.sleep(0.2)
        freed = await _exchange(server, NEIGHBOUR, _get("/healthz"))
        return {"full": full, "freed": freed}
    finally:
        for _, writer in half_sent:
            writer.close()


def test_a_full_server_answers_503_with_the_common_body(small_server: ServerProcess) -> None:
    result = asyncio.run(_fill(small_server))
    status, headers, body = result["full"]
    assert status == 503 and headers["content-type"] == "application/json"
    assert int(headers["retry-after"]) >= 1
    assert _detail(body)["type"] == "server_full"
    assert result["freed"][0] == 200


async def _crowd(server: ServerProcess) -> dict[str, Any]:
    """The hoarder takes its share (8 of 16), the neighbour tries to; a third address asks."""
    half_sent: list[tuple[Any, Any]] = []
    try:
        await _half_send(server, HOARDER, SHARE, half_sent)
        await _half_send(server, NEIGHBOUR, SHARE // 2, half_sent)
        await asyncio.sleep(0.2)
        over = await _exchange(server, NEIGHBOUR, _get("/healthz"))
        third = await _exchange(server, "127.0.0.14", _get("/healthz"))
        return {"over": over, "third": third}
    finally:
        for _, writer in half_sent:
            writer.close()


def test_an_address_share_shrinks_as_the_server_fills(small_server: ServerProcess) -> None:
    """Two addresses at the full share would fill the server; the second gets half of what is
    left (4 of 8), so a third is still served."""
    result = asyncio.run(_crowd(small_server))
    status, _, body = result["over"]
    assert status == 429 and _detail(body)["type"] == "too_many_connections", body
    assert result["third"][0] == 200


async def _refused_and_held(server: ServerProcess) -> dict[str, Any]:
    """The hoarder takes its share, then opens 24 more connections (each refused as it opens)
    and keeps them open without reading; a neighbour asks at once."""
    half_sent: list[tuple[Any, Any]] = []
    try:
        await _half_send(server, HOARDER, SHARE, half_sent)
        await asyncio.sleep(0.2)
        refused = [await _open(server, HOARDER) for _ in range(24)]
        half_sent += refused
        neighbour = await _exchange(server, NEIGHBOUR, _get("/healthz"))
        answers = [await reader.read() for reader, _ in refused[:2]]
        return {"neighbour": neighbour, "answers": answers}
    finally:
        for _, writer in half_sent:
            writer.close()


def test_connections_refused_as_they_open_hold_no_place(small_server: ServerProcess) -> None:
    """A connection refused as it opens (past its address's share, or a full server) is
    closed once its answer is written, not held a second: one address opening connections
    past its share had held thousands at once and filled the server for everyone."""
    result = asyncio.run(_refused_and_held(small_server))
    assert result["neighbour"][0] == 200, result["neighbour"]
    assert all(b"too_many_connections" in answer for answer in result["answers"])
