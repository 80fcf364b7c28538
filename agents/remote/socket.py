"""``RoundSocket``: one agent's WebSocket to one auction's remote rounds
(``WS /auctions/{id}/rounds/socket``), the alternative to a long poll and a PUT per round.

The server pushes every round as it opens and the auction's end; an upload is one message and
its answer the PUT's status and body. A dropped connection is opened again with exponential
backoff (503 and 429 handshakes honour Retry-After) until ``give_up_s`` has passed, then
``ServerGoneError`` names the server; an upload whose answer was lost is sent again with the
same bytes, which the server answers as it answered them the first time; if the auction has
ended meanwhile (its socket closes for good), ``AuctionEndedError`` says so, and the upload's
PUT gets its answer. A socket silent for
``RESYNC_S`` while the agent waits for a round is opened again too (the server sends the current
round on every connection). Frames are counted in the client's ``Traffic``."""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import time
from types import TracebackType
from typing import Any

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

from agents.remote.client import (
    GIVE_UP_S,
    HTTP_TIMEOUT_S,
    RETRY_STATUSES,
    Backoff,
    RemoteError,
    ServerGoneError,
    Traffic,
    retry_after_s,
)

MAX_FRAME_BYTES = 1 << 20
"""Largest frame the agent reads (a round is about 7 KB)."""
RESYNC_S = 60.0
"""Without a frame for this long while waiting for a round, the agent opens the socket again
(the server sends the current round on every connection)."""


class _DroppedError(Exception):
    """The connection went away before the answer came."""


class SocketsFullError(RemoteError):
    """The server refused the handshake with 429 for the round sockets of this host (its share
    is taken: other agents on this host hold them): the agent plays over HTTP instead."""


class AuctionEndedError(RemoteError):
    """The auction ended and its socket closed before an upload was answered: the upload's
    PUT (the same bytes) gets the answer the server gave it, or 410."""


def socket_url(server: str, auction_id: int) -> str:
    """The round socket's URL on an ``http://`` or ``https://`` server."""
    base = server.rstrip("/")
    if base.startswith("https://"):
        base = "wss://" + base[len("https://") :]
    elif base.startswith("http://"):
        base = "ws://" + base[len("http://") :]
    return f"{base}/auctions/{auction_id}/rounds/socket"


def _ready(state: dict[str, Any], after: int) -> bool:
    """Worth handing on to an agent that handled round ``after``: a newer round open, or the
    end."""
    if _ended(state):
        return True
    return state["status"] == "open" and (state["round"] or 0) > after


def _ended(state: dict[str, Any]) -> bool:
    return state["auction_status"] not in ("pending", "running")


class RoundSocket:
    """One agent's round socket (see the module docstring); use it as an async context."""

    def __init__(
        self,
        server: str,
        auction_id: int,
        token: str | None,
        *,
        give_up_s: float = GIVE_UP_S,
        rng: random.Random | None = None,
        traffic: Traffic | None = None,
    ) -> None:
        self.server = server
        self.url = socket_url(server, auction_id)
        self.token = token
        self.give_up_s = give_up_s
        self.traffic = traffic or Traffic()
        self._rng = rng or random.Random(0)
        self._ws: ClientConnection | None = None
        self._reader: asyncio.Task[None] | None = None
        self._latest: dict[str, Any] | None = None
        self._changed = asyncio.Event()
        self._answers: dict[tuple[int, int], asyncio.Future[tuple[int, Any]]] = {}
        self.resync_s = RESYNC_S

    async def __aenter__(self) -> RoundSocket:
        await self._ensure()
        return self

    async def __aexit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        await self.close()

    async def close(self) -> None:
        if self._ws is not None:
            with contextlib.suppress(Exception):
                await self._ws.close()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader
        self._ws, self._reader = None, None

    async def next_round(self, after: int) -> dict[str, Any]:
        """The auction's state once a round above ``after`` is open or the auction has ended
        (the round as ``GET .../rounds/current`` shows it)."""
        while True:
            if self._latest is not None and _ready(self._latest, after):
                return self._latest
            ws = await self._ensure()
            changed = self._changed
            if self._ws is not None and not (self._latest and _ready(self._latest, after)):
                try:
                    await asyncio.wait_for(changed.wait(), self.resync_s)
                except TimeoutError:  # silent for too long: start afresh
                    with contextlib.suppress(Exception):
                        await ws.close()

    async def upload(self, round_number: int, model_id: int, body: bytes) -> tuple[int, Any]:
        """Send a fine-tuned manifest (its JSON bytes) for the round: the server's status and
        answer body, as a PUT would get them."""
        text = json.dumps(
            {
                "type": "upload",
                "round": round_number,
                "model_id": model_id,
                "manifest": body.decode(),
            },
            separators=(",", ":"),
        )
        backoff = Backoff(time.monotonic() + self.give_up_s, self._rng, self.traffic)
        while True:
            ws = await self._ensure(backoff.give_up_at)
            key = (round_number, model_id)
            answer: asyncio.Future[tuple[int, Any]] = asyncio.get_running_loop().create_future()
            self._answers[key] = answer
            self.traffic.requests += 1
            try:
                await ws.send(text)
                self.traffic.bytes_up += len(body)
                status, reply = await asyncio.wait_for(answer, HTTP_TIMEOUT_S)
            except (ConnectionClosed, _DroppedError, TimeoutError) as exc:
                if self._latest is not None and _ended(self._latest):
                    raise AuctionEndedError(
                        f"auction at {self.url} ended before the upload of round "
                        f"{round_number} was answered on its socket"
                    ) from exc
                if backoff.exhausted():
                    raise ServerGoneError(
                        f"the server at {self.server} did not answer the upload of round "
                        f"{round_number} ({type(exc).__name__}); gave up after "
                        f"{self.give_up_s:.0f} s"
                    ) from exc
            else:
                if status not in RETRY_STATUSES:
                    return status, reply
                if backoff.exhausted():
                    raise ServerGoneError(
                        f"the server at {self.server} kept answering {status} to the upload of "
                        f"round {round_number}; gave up after {self.give_up_s:.0f} s"
                    )
            finally:
                self._answers.pop(key, None)
            await backoff.pause()

    async def _ensure(self, give_up: float | None = None) -> ClientConnection:
        """The open connection, opened (again) if need be."""
        if self._ws is not None:
            return self._ws
        give_up = time.monotonic() + self.give_up_s if give_up is None else give_up
        backoff = Backoff(give_up, self._rng, self.traffic)
        headers = {} if self.token is None else {"Authorization": f"Bearer {self.token}"}
        while True:
            retry_after = 0.0
            try:
                ws = await connect(
                    self.url,
                    additional_headers=headers,
                    compression=None,
                    max_size=MAX_FRAME_BYTES,
                    open_timeout=HTTP_TIMEOUT_S,
                )
            except InvalidStatus as exc:
                status = exc.response.status_code
                if status == 429 and b"round sockets" in (exc.response.body or b""):
                    raise SocketsFullError(
                        f"round socket {self.url}: this host's share is taken"
                    ) from exc
                if status not in RETRY_STATUSES:
                    shown = (exc.response.body or b"").decode(errors="replace")[:500]
                    raise RemoteError(f"round socket {self.url}: {status} {shown}") from exc
                retry_after = retry_after_s(exc.response.headers.get("Retry-After"))
                failure = f"kept answering {status}"
            except (OSError, InvalidHandshake, TimeoutError) as exc:
                failure = f"did not answer ({type(exc).__name__}: {exc})"
            else:
                self._ws = ws
                self._reader = asyncio.create_task(self._read(ws))
                return ws
            if backoff.exhausted(retry_after):
                raise ServerGoneError(
                    f"the server at {self.server} {failure} on {self.url}; gave up after "
                    f"{self.give_up_s:.0f} s"
                )
            await backoff.pause(retry_after)

    async def _read(self, ws: ClientConnection) -> None:
        """Hand every frame on: rounds to ``next_round``, answers to their uploads."""
        try:
            async for frame in ws:
                self.traffic.bytes_down += len(frame)
                message = json.loads(frame)
                if message.get("type") == "round":
                    self._latest = message["body"]
                    self._wake()
                elif message.get("type") == "answer":
                    waiting = self._answers.get((message["round"], message["model_id"]))
                    if waiting is not None and not waiting.done():
                        waiting.set_result((message["status"], message["body"]))
        except (ConnectionClosed, ValueError, KeyError):  # gone, or not the protocol: reconnect
            pass
        finally:
            if self._ws is ws:
                self._ws = None
            for waiting in self._answers.values():
                if not waiting.done():
                    waiting.set_exception(_DroppedError())
            self._wake()

    def _wake(self) -> None:
        self._changed.set()
        self._changed = asyncio.Event()
