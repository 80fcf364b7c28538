"""``RoundSocket`` against a scripted WebSocket server on loopback: rounds handed on in order, an
upload whose connection drops is sent again with the same bytes on a new connection, a socket
that falls silent is opened again, busy handshakes are retried, a missing auction and a gone
server end with errors naming them."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from http import HTTPStatus
from typing import Any

import pytest
from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from agents.remote import RemoteError, RoundSocket, ServerGoneError, socket_url


def state(round_: int | None, status: str, auction_status: str = "running") -> dict[str, Any]:
    return {"round": round_, "status": status, "auction_status": auction_status, "asked": [1]}


def frame(body: dict[str, Any]) -> str:
    return json.dumps({"type": "round", "body": body})


Handler = Callable[[ServerConnection], Any]


@asynccontextmanager
async def scripted(
    handler: Handler, refuse: Callable[[int], Response | None] | None = None
) -> AsyncIterator[str]:
    """A loopback server running ``handler`` per connection (``refuse(n)`` may answer the
    n-th handshake instead); yields its http:// URL."""
    handshakes = 0

    def process_request(connection: ServerConnection, request: Request) -> Response | None:
        nonlocal handshakes
        handshakes += 1
        return None if refuse is None else refuse(handshakes)

    async with serve(handler, "127.0.0.1", 0, process_request=process_request) as server:
        port = server.sockets[0].getsockname()[1]
        yield f"http://127.0.0.1:{port}"


def test_the_socket_url_follows_the_server_scheme() -> None:
    assert socket_url("http://h:8000/", 7) == "ws://h:8000/auctions/7/rounds/socket"
    assert socket_url("https://h", 7) == "wss://h/auctions/7/rounds/socket"


def test_rounds_are_handed_on_in_order_and_a_lost_answer_is_asked_again() -> None:
    uploads: list[str] = []
    tokens: list[str | None] = []
    connections = 0

    async def handler(ws: ServerConnection) -> None:
        nonlocal connections
        connections += 1
        tokens.append(ws.request.headers.get("Authorization") if ws.request else None)
        await ws.send(frame(state(1, "closed")))
        await ws.send(frame(state(2, "open")))
        async for text in ws:
            message = json.loads(text)
            uploads.append(message["manifest"])
            if connections == 1:  # drop the first connection before answering
                await ws.close(1011)
                return
            answer = {"type": "answer", "round": message["round"], "model_id": message["model_id"]}
            await ws.send(json.dumps({**answer, "status": 200, "body": {"outcome": "accepted"}}))
            await ws.send(frame(state(2, "closed", "finished")))

    async def run() -> tuple[dict[str, Any], tuple[int, Any], dict[str, Any]]:
        async with scripted(handler) as url, RoundSocket(url, 5, "tok", give_up_s=10) as socket:
            opened = await socket.next_round(after=1)
            answer = await socket.upload(2, 1, b'{"m": 1}')
            ended = await socket.next_round(after=2)
            return opened, answer, ended

    opened, answer, ended = asyncio.run(run())
    assert (opened["round"], opened["status"]) == (2, "open")
    assert answer == (200, {"outcome": "accepted"})
    assert ended["auction_status"] == "finished"
    assert uploads == ['{"m": 1}', '{"m": 1}'] and connections == 2  # the same bytes again
    assert tokens == ["Bearer tok", "Bearer tok"]


def test_busy_handshakes_are_retried_and_a_missing_auction_is_an_error() -> None:
    async def handler(ws: ServerConnection) -> None:
        await ws.send(frame(state(1, "open")))
        await ws.wait_closed()

    def refuse_twice(n: int) -> Response | None:
        if n > 2:
            return None
        return _response(HTTPStatus.SERVICE_UNAVAILABLE, {"Retry-After": "0"}, b"busy")

    def missing(n: int) -> Response | None:
        return _response(HTTPStatus.NOT_FOUND, {}, b'{"detail":"auction 5 does not exist"}')

    async def run() -> tuple[dict[str, Any], int]:
        async with scripted(handler, refuse_twice) as url:
            socket = RoundSocket(url, 5, None, give_up_s=10)
            async with socket:
                got = await socket.next_round(after=0)
            return got, socket.traffic.retries

    got, retries = asyncio.run(run())
    assert got["round"] == 1 and retries == 2

    async def refused() -> None:
        async with scripted(handler, missing) as url, RoundSocket(url, 5, None):
            pass

    with pytest.raises(RemoteError, match=r"404 .*auction 5 does not exist"):
        asyncio.run(refused())


def test_a_server_that_is_gone_is_named_after_give_up() -> None:
    async def run() -> None:
        async with scripted(lambda ws: ws.close()) as url:
            pass  # the server is stopped: nothing listens on its port any more
        async with RoundSocket(url, 5, None, give_up_s=0.3):
            pass

    with pytest.raises(ServerGoneError, match=r"127\.0\.0\.1.*gave up after 0 s"):
        asyncio.run(run())


def test_a_silent_socket_is_opened_again() -> None:
    connections = 0

    async def handler(ws: ServerConnection) -> None:
        nonlocal connections
        connections += 1
        await ws.send(frame(state(1, "open" if connections == 1 else "closed")))
        if connections > 1:
            await ws.send(frame(state(2, "open")))
        await ws.wait_closed()  # then silence

    async def run() -> dict[str, Any]:
        async with scripted(handler) as url, RoundSocket(url, 5, None) as socket:
            socket.resync_s = 0.2
            assert (await socket.next_round(after=0))["round"] == 1
            return await socket.next_round(after=1)

    got = asyncio.run(run())
    assert (got["round"], got["status"]) == (2, "open") and connections == 2


def _response(status: HTTPStatus, headers: dict[str, str], body: bytes) -> Response:
    return Response(status.value, status.phrase, Headers(headers), body)
