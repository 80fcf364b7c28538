"""The round socket: ``WS /auctions/{id}/rounds/socket``, the remote rounds of one auction over
one WebSocket per agent.

The same protocol as ``GET .../rounds/current`` and ``PUT .../rounds/{round}/models/{model_id}``,
without an HTTP request per step: the server pushes every round as it opens (and the auction's
end), the agent sends its uploads on the same connection and gets each answer there. A pushed
round is the long poll's JSON body, an upload's answer the PUT's status and body, so both
transports share every check, every counter and every stored outcome
(``server.auctions.uploads``):

* server → agent: ``{"type": "round", "body": <RoundPublic>}`` on connecting (the auction's
  newest round, whatever its status), then whenever a round opens, and once the auction has
  ended, after which the server closes the socket (code 1000) as soon as the upload it is
  handling, if any, is answered (an upload sent after that close is answered by its PUT);
* agent → server: ``{"type": "upload", "round": R, "model_id": M, "manifest": "<JSON text>"}``,
  the manifest as the JSON *text* a PUT would carry: its bytes are what is checked, hashed for
  the one-upload-per-round rule and counted;
* server → agent: ``{"type": "answer", "round": R, "model_id": M, "status": S, "body": B}``, S and
  B exactly the PUT's (200 with ``UploadPublic``; 4xx with ``{"detail": [...]}``).

Identity is the handshake's ``Authorization: Bearer <participant token>``, checked on every
upload as the PUT checks it. Limits: ``MAX_SOCKETS`` open sockets of the auction's patrons per
API process and ``MAX_WATCHER_SOCKETS`` of anyone else (beyond, the
handshake is answered 503 with Retry-After), frames up to ``MAX_FRAME_BYTES`` (a socket that
sends a bigger one is closed, code 1009: by uvicorn under ``srd serve``, by the app under any
other server), a manifest up to the PUT's upload limit (413), uploads handled one at a time per
socket and counted in their token's uploads in flight with its PUTs (429 past its share,
``server.api.limits``), a token bucket of ``BURST`` messages refilled at ``REFILL_PER_S`` per
socket (beyond it the socket is closed, code 1008), and every message counted against its
address's request rate with its requests and its other sockets' messages, as an upload by PUT
counts (its turn taken ahead, never held; a second of the rate beyond it the message is
answered 429 unread and the socket closed, code 1013, as HTTP answers 429 and closes the
connection). A dead peer is dropped by the server's WebSocket pings; a socket whose rounds
cannot be read is closed with 1011, for the agent to reconnect.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
from collections.abc import Awaitable, Callable
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.websockets import WebSocket, WebSocketDisconnect, WebSocketState

from server.api.body import BodyRefusedError, parse_strict_json
from server.api.connections import TokenBucket
from server.api.errors import RequestError, capped, database_unavailable, error_item
from server.api.limits import CLOSE_TRY_AGAIN_LATER
from server.api.schemas import MAX_FINE_TUNE_ROUNDS, MAX_ROW_ID
from server.live.rounds import MAX_WAIT_S, Published, RoundWatcher, TooManyWaitersError
from server.store.db import first_line, is_database_outage
from server.store.tables import utcnow

log = logging.getLogger("srd.rounds")

MAX_SOCKETS = 1024
"""Round sockets of patrons (a participant token with a model in the auction) per process."""
MAX_WATCHER_SOCKETS = 256
"""Round sockets of anyone else (no token, or not the auction's) per process: apart from the
patrons', so that watchers, or many addresses each within its share, cannot take theirs."""
UPLOAD_MAX_BYTES = 65_536
"""Largest manifest an upload may carry (the PUT's body limit)."""
MAX_FRAME_BYTES = 2 * UPLOAD_MAX_BYTES + 4096
"""Largest frame the server reads (a manifest's JSON text escaped inside a message)."""
BURST, REFILL_PER_S = 64, 16.0
"""The message allowance of one socket: a burst, refilled per second."""
RETRY_AFTER_S = 1
"""Retry-After of a refused handshake, and the pause of a pusher refused a wait."""
CLOSE_TOO_MANY_MESSAGES = 1008
"""Close code (policy violation) of a socket over its message allowance."""
CLOSE_TOO_BIG = 1009
"""Close code (message too big) of a socket that sent a frame over ``MAX_FRAME_BYTES``."""
CLOSE_RESTART = 1012
"""Close code (service restart) of the sockets of a server shutting down: reconnect."""
MAX_REASON_BYTES = 123
"""The longest close reason a WebSocket close frame carries."""


class _DrainingError(Exception):
    """The server is shutting down: no round will be pushed on this socket any more."""


class UploadMessage(BaseModel):
    """An upload sent on the socket (the PUT's path and body in one message)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    type: Literal["upload"]
    round: Annotated[int, Field(ge=1, le=MAX_FINE_TUNE_ROUNDS)]
    model_id: Annotated[int, Field(ge=1, le=MAX_ROW_ID)]
    manifest: str
    """The manifest's JSON text, as a PUT body would carry it."""


class SocketLimitError(RuntimeError):
    """This process already holds ``MAX_SOCKETS`` round sockets."""


UploadHandler = Callable[[int, int, bytes, datetime], Awaitable[bytes]]
"""``(round, model_id, manifest bytes, arrival) -> answer body``: the PUT's service call
(RequestError for a refusal)."""
MessageAllowance = Callable[[int], RequestError | None]
"""Counts a received message of so many bytes against its address's request rate: the refusal
past it."""


async def _not_a_patron() -> bool:
    return False


class _Socket:
    """One accepted socket: frames sent one at a time (pusher and answers share it)."""

    def __init__(self, websocket: WebSocket) -> None:
        self.websocket = websocket
        self._lock = asyncio.Lock()
        self.answering = asyncio.Lock()
        """Held while an upload is handled: the end of the auction waits for its answer."""
        self.patron = False
        """Its waits count in the patrons' share (see ``RoundSockets.serve``)."""
        self.is_patron: Callable[[], Awaitable[bool]] = _not_a_patron

    async def send(self, text: str) -> None:
        async with self._lock:
            try:
                await self.websocket.send_text(text)
            except RuntimeError as exc:  # the protocol closed it under us (a client's frame
                # that was not UTF-8: 1007) before its disconnect reached this task
                raise WebSocketDisconnect(1006, "closed by the protocol") from exc

    async def close(self, code: int, reason: str = "") -> None:
        async with self._lock:
            await self.websocket.close(code=code, reason=reason)


class RoundSockets:
    """The round sockets of one API process: their count, and each socket's conversation."""

    def __init__(self, watcher: RoundWatcher) -> None:
        self._watcher = watcher
        self.open = {True: 0, False: 0}
        """Open sockets: patrons' (True) and others' (False)."""

    def reserve(self, *, patron: bool) -> None:
        """Count a socket about to be accepted (SocketLimitError beyond ``MAX_SOCKETS`` of
        patrons, or ``MAX_WATCHER_SOCKETS`` of others)."""
        most = MAX_SOCKETS if patron else MAX_WATCHER_SOCKETS
        if self.open[patron] >= most:
            whose = "patrons'" if patron else "watchers' (no patron's token)"
            raise SocketLimitError(f"{most} {whose} round sockets are open already")
        self.open[patron] += 1

    def release(self, patron: bool) -> None:
        self.open[patron] -= 1

    async def serve(
        self,
        websocket: WebSocket,
        auction_id: int,
        first: Published,
        upload: UploadHandler,
        patron: bool,
        is_patron: Callable[[], Awaitable[bool]],
        allowance: MessageAllowance,
    ) -> None:
        """Run one accepted socket until the auction ends or the agent goes away: a pusher
        task sends the rounds, this task answers the uploads. The pusher's waits count in
        the patrons' share if the socket is a patron's (``patron``; else, once everyone's is
        full, if ``is_patron`` says so), in everyone's otherwise."""
        socket = _Socket(websocket)
        socket.patron, socket.is_patron = patron, is_patron
        pusher = asyncio.create_task(self._push_or_close(socket, auction_id, first))
        try:
            await self._answer_uploads(socket, upload, allowance)
        except (WebSocketDisconnect, RuntimeError):  # gone, or closed by the pusher
            pass
        finally:
            pusher.cancel()
            with contextlib.suppress(asyncio.CancelledError, WebSocketDisconnect, RuntimeError):
                await pusher

    async def _push_or_close(self, socket: _Socket, auction_id: int, first: Published) -> None:
        """``_push``; if it fails (the database is unavailable), the socket is closed with
        1011 so that the agent reconnects rather than waits for rounds that never come."""
        try:
            await self._push(socket, auction_id, first)
        except (asyncio.CancelledError, WebSocketDisconnect):
            raise
        except Exception as exc:
            if socket.websocket.application_state == WebSocketState.DISCONNECTED:
                return  # the answering task closed it meanwhile (a flood, a frame too big)
            if is_database_outage(exc):
                log.warning("round socket of auction %d: %s; closed", auction_id, exc)
            else:
                log.exception("pushing the rounds of auction %d failed", auction_id)
            with contextlib.suppress(Exception):
                await socket.close(1011, "the server could not read the rounds; reconnect")

    async def _push(self, socket: _Socket, auction_id: int, published: Published | None) -> None:
        """Send the first state, then every round that opens, then the end (and close)."""
        after = 0
        while published is not None:
            await socket.send(_round_frame(published))
            if published.auction_over:
                async with socket.answering:  # an upload being handled gets its answer first
                    await socket.close(1000, "the auction has ended")
                return
            if published.open and published.round is not None:
                after = max(after, published.round)
            try:
                published = await self._next(socket, auction_id, after)
            except _DrainingError:
                await socket.close(CLOSE_RESTART, "the server is restarting; reconnect")
                return
        await socket.close(1011, "the auction is gone")

    async def _next(self, socket: _Socket, auction_id: int, after: int) -> Published | None:
        """The next state worth pushing: a round above ``after`` opened, or the end (its wait
        counted in the socket's share, see ``serve``)."""
        while True:
            try:
                published = await self._watcher.published(
                    auction_id, wait_s=MAX_WAIT_S, after=after, patron=socket.patron
                )
            except TooManyWaitersError:
                if not socket.patron and await socket.is_patron():
                    socket.patron = True
                else:
                    await asyncio.sleep(RETRY_AFTER_S)
                continue
            if published is None or published.ready(after):
                return published
            if self._watcher.draining:
                raise _DrainingError

    async def _answer_uploads(
        self, socket: _Socket, upload: UploadHandler, allowance: MessageAllowance
    ) -> None:
        bucket = TokenBucket(BURST, REFILL_PER_S)
        while True:
            message = await socket.websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            if not bucket.take():
                await socket.close(
                    CLOSE_TOO_MANY_MESSAGES,
                    f"more than {BURST} messages at once ({REFILL_PER_S:g} per second)",
                )
                return
            text = message.get("text")
            data = message.get("bytes") if text is None else text.encode("utf-8", "surrogatepass")
            size = len(data or b"")  # bytes, not characters: a character is up to four
            refused = allowance(size)
            if refused is not None:  # answered unread, and closed: as HTTP answers and closes
                await socket.send(_refusal(None, None, refused))
                reason = str(refused.items[0]["msg"]).encode()[:MAX_REASON_BYTES]
                await socket.close(CLOSE_TRY_AGAIN_LATER, reason.decode(errors="ignore"))
                return
            if size > MAX_FRAME_BYTES:  # whatever uvicorn's own frame cap let through
                await socket.close(CLOSE_TOO_BIG, f"a frame is at most {MAX_FRAME_BYTES} bytes")
                return
            if text is None:
                await socket.send(
                    _error(None, 422, "send uploads as text frames of JSON", ("message",))
                )
                continue
            async with socket.answering:
                await socket.send(await _handle(data or b"", upload, utcnow()))


async def _handle(text: bytes, upload: UploadHandler, arrived: datetime) -> str:
    """The answer frame of one received text message (its UTF-8 bytes)."""
    try:  # as strictly as a body: a key twice, NaN, too long an integer, too deep
        raw = parse_strict_json(text)
    except BodyRefusedError as exc:
        msg = _called(exc.msg, "message")
        return _error(None, exc.status, msg, ("message", *exc.loc[1:]), exc.kind)
    try:
        message = UploadMessage.model_validate(raw)
    except ValidationError as exc:
        items = capped(
            error_item(
                str(e["msg"]), loc=("message", *(str(p) for p in e["loc"])), kind=str(e["type"])
            )
            for e in exc.errors()
        )
        ids = raw if isinstance(raw, dict) else {}
        return _frame(_int(ids.get("round")), _int(ids.get("model_id")), 422, {"detail": items})
    body = message.manifest.encode("utf-8", "surrogatepass")
    if len(body) > UPLOAD_MAX_BYTES:
        return _error(
            message,
            413,
            f"an upload is at most {UPLOAD_MAX_BYTES} bytes",
            ("message", "manifest"),
            "body_size",
        )
    try:
        parse_strict_json(body)
    except BodyRefusedError as exc:
        loc = ("message", "manifest", *exc.loc[1:])
        return _error(message, exc.status, _called(exc.msg, "manifest"), loc, exc.kind)
    try:
        answer = await upload(message.round, message.model_id, body, arrived)
    except RequestError as exc:
        return _refusal(message.round, message.model_id, exc)
    except Exception as exc:
        if is_database_outage(exc):  # as a PUT hears it: 503, for the agent to try again
            log.warning("an upload on a round socket met a database outage: %s", first_line(exc))
            return _refusal(message.round, message.model_id, database_unavailable(exc))
        # a fault of ours: the agent hears 500, as a PUT would, and may retry
        log.exception("an upload on a round socket failed")
        return _error(message, 500, "internal server error", ("message",), "internal")
    return (
        f'{{"type":"answer","round":{message.round},"model_id":{message.model_id},'
        f'"status":200,"body":{answer.decode()}}}'
    )


def _called(msg: str, what: str) -> str:
    """A body check's refusal in a message's terms: what it calls the body is ``what``."""
    return re.sub(r"\bbody\b", what, msg)


def _refusal(round_number: int | None, model_id: int | None, exc: RequestError) -> str:
    """The answer frame of a refusal, its locations in the message's terms."""
    items = [{**item, "loc": _message_loc(item["loc"])} for item in exc.items]
    return _frame(round_number, model_id, exc.status, {"detail": items})


def _message_loc(loc: list[str | int]) -> list[str | int]:
    """A PUT's error location in the message's terms: its path parameters are the message's
    fields (but the auction's id, which is the socket's path), its body the message's
    ``manifest``."""
    if loc == ["path", "auction_id"]:
        return loc
    if loc[:1] == ["path"]:
        return ["message", *loc[1:]]
    if loc[:1] == ["body"]:
        return ["message", "manifest", *loc[1:]]
    return loc


def _int(value: Any) -> int | None:
    """An id to echo back: an integer a round or a version could have, else none."""
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_ROW_ID:
        return value
    return None


def _error(
    message: UploadMessage | None,
    status: int,
    msg: str,
    loc: tuple[str | int, ...],
    kind: str = "error",
) -> str:
    return _frame(
        None if message is None else message.round,
        None if message is None else message.model_id,
        status,
        {"detail": [error_item(msg, loc=loc, kind=kind)]},
    )


def _frame(round_number: int | None, model_id: int | None, status: int, body: Any) -> str:
    return json.dumps(
        {
            "type": "answer",
            "round": round_number,
            "model_id": model_id,
            "status": status,
            "body": body,
        },
        separators=(",", ":"),
    )


def _round_frame(published: Published) -> str:
    return f'{{"type":"round","body":{published.body.decode()}}}'
