"""``RemoteAgent``: one participant with one model over HTTP. It ``submit``s the model, finds
the auctions it entered, and ``play``s one to the end: in each round it receives the round,
runs its fine-tuner and uploads the result with its token. Its ``transport`` says how rounds
travel: ``"http"`` (a long poll and a PUT per round) or ``"websocket"`` (one round socket for
the auction, ``agents.remote.socket``)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from agents.manifest import Manifest, parse_manifest
from agents.remote.client import HTTP_TIMEOUT_S, Client, RemoteError
from agents.remote.fine_tuners import FineTuner, RoundInfo, faithful_fine_tune
from agents.remote.socket import AuctionEndedError, RoundSocket, SocketsFullError

Transport = Literal["http", "websocket"]
TRANSPORTS: tuple[Transport, ...] = ("http", "websocket")

ROUND_WAIT_S = 25.0
"""Long-poll of one round request (the server allows up to 30 s)."""


@dataclass
class RoundLog:
    """What one agent did in one round (times in seconds, monotonic clock)."""

    round: int
    received_at: float
    fine_tune_s: float
    upload_s: float
    outcome: str
    """accepted | refused | held | late | answered before (this round was answered by an
    earlier run of the agent: its answer stands)."""


@dataclass
class Uploads:
    """An agent's uploads by the server's answer."""

    accepted: int = 0
    refused: int = 0
    late: int = 0
    held: int = 0
    """Within the review margin of a bar: kept for an inspector, the previous version bids."""


class RemoteAgent:
    """One participant with one model (see the module docstring)."""

    def __init__(
        self,
        client: Client,
        manifest: Manifest,
        *,
        fine_tuner: FineTuner = faithful_fine_tune,
        token: str | None = None,
        model_id: int | None = None,
        transport: Transport = "http",
    ) -> None:
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, not {transport!r}")
        self.client = client
        self.transport: Transport = transport
        self.current = manifest
        """The version the server lets this patron bid with (updated on every acceptance, and
        read from the server when an auction starts with another: a resumed agent)."""
        self.current_id = model_id
        """The model id of ``current``, when known."""
        self._stale = False
        self.error: str | None = None
        """Why the agent stopped playing, if an error stopped it (set by its population)."""
        self.fine_tuner = fine_tuner
        self.token = token
        self.model_id = model_id
        self.accepted_at_submit: bool | None = None
        self.uploads = Uploads()
        self.log: list[RoundLog] = []
        self.reasons: list[dict[str, str]] = []
        """The screener's reasons of every refused upload."""

    async def submit(self) -> dict[str, Any]:
        """``POST /submit`` the manifest (with the token for a later version); keeps the model
        id and the token. Not resent if it may have arrived (a resend would be a second
        version)."""
        answer: dict[str, Any] = await self.client.json(
            "POST",
            "/submit",
            body=self.current.model_dump_json().encode(),
            token=self.token,
            resend=False,
        )
        self.model_id = self.current_id = int(answer["model_id"])
        self.token = answer.get("token") or self.token
        self.accepted_at_submit = bool(answer["accepted"])
        return answer

    async def auctions(self) -> list[int]:
        """The auctions this agent's model entered, newest first."""
        model = await self.client.json("GET", f"/models/{self.submitted_id}")
        return [int(a) for a in model.get("auctions", [])]

    @property
    def submitted_id(self) -> int:
        """The model id (RemoteError before ``submit``)."""
        if self.model_id is None:
            raise RemoteError("the agent has no model id: submit first")
        return self.model_id

    async def play(
        self, auction_id: int, on_round: Callable[[RoundLog], None] | None = None
    ) -> None:
        """Answer every round of the auction this agent is asked in, until it ends (or the
        patron leaves it by buying or quitting)."""
        auction = await self.client.json("GET", f"/auctions/{auction_id}")
        if self.submitted_id not in auction["model_ids"]:
            raise RemoteError(f"model {self.submitted_id} is not a patron of auction {auction_id}")
        position = auction["model_ids"].index(self.submitted_id)
        await self._bid_with(auction, position)
        if self.transport == "websocket":
            try:
                async with RoundSocket(
                    self.client.server,
                    auction_id,
                    self.token,
                    give_up_s=self.client.give_up_s,
                    traffic=self.client.traffic,
                ) as socket:
                    await self._play(auction_id, position, on_round, socket)
                return
            except SocketsFullError:
                pass  # this host's share of round sockets is taken: long polls instead
        await self._play(auction_id, position, on_round, None)

    async def _bid_with(self, auction: dict[str, Any], position: int) -> None:
        """Make ``current`` the version the auction lets this patron bid with now (read from
        the server when it is not the one this agent holds: an agent resumed with ``token``
        and ``model_id``, or that played another auction since)."""
        bidding = auction.get("current_model_ids") or auction["model_ids"]
        version_id = int(bidding[position])
        if version_id != self.current_id:
            model = await self.client.json("GET", f"/models/{version_id}")
            self.current, self.current_id = parse_manifest(model["manifest"]), version_id

    async def _play(
        self,
        auction_id: int,
        position: int,
        on_round: Callable[[RoundLog], None] | None,
        socket: RoundSocket | None,
    ) -> None:
        after = 0
        while True:
            if socket is not None:
                state = await socket.next_round(after)
            else:
                response = await self.client.request(
                    "GET",
                    f"/auctions/{auction_id}/rounds/current?wait={ROUND_WAIT_S}&after={after}",
                    token=self.token,  # a patron's long polls have a share of their own
                    timeout_s=HTTP_TIMEOUT_S + ROUND_WAIT_S,
                )
                if not response.is_success:
                    raise RemoteError(f"round of auction {auction_id}: {response.text[:500]}")
                state = response.json()
            received = time.monotonic()
            if state["auction_status"] not in ("pending", "running"):
                return
            if state["status"] != "open" or state["round"] <= after:
                continue
            after = state["round"]
            if self.submitted_id not in state["asked"]:
                return  # bought or quit: never asked again
            entry = await self._answer(auction_id, state, position, received, socket)
            if on_round is not None:
                on_round(entry)

    async def _send(
        self, auction_id: int, round_number: int, body: bytes, socket: RoundSocket | None
    ) -> tuple[int, Any]:
        """Upload ``body`` for the round: the server's status and answer (JSON)."""
        if socket is not None:
            try:
                return await socket.upload(round_number, self.submitted_id, body)
            except AuctionEndedError:
                pass  # the same bytes as a PUT: the answer the server gave them, or 410
        response = await self.client.request(
            "PUT",
            f"/auctions/{auction_id}/rounds/{round_number}/models/{self.submitted_id}",
            body=body,
            token=self.token,
        )
        try:
            return response.status_code, response.json()
        except ValueError:
            return response.status_code, response.text[:500]

    async def _answer(
        self,
        auction_id: int,
        state: dict[str, Any],
        position: int,
        received: float,
        socket: RoundSocket | None,
    ) -> RoundLog:
        if self._stale:
            await self._bid_with(await self.client.json("GET", f"/auctions/{auction_id}"), position)
            self._stale = False
        info = RoundInfo.from_state(state, position)
        # In a thread: a slow fine-tuner must not hold the other agents of this event loop.
        tuned = await asyncio.to_thread(self.fine_tuner, self.current, info)
        tuned_at = time.monotonic()
        status, answer = await self._send(
            auction_id, info.round, tuned.model_dump_json().encode(), socket
        )
        outcome = "error"
        if status == 200:
            outcome = answer["outcome"]
            if answer["accepted"]:
                self.current, self.current_id = tuned, int(answer["model_id"])
                self.uploads.accepted += 1
            elif outcome == "held":
                self.uploads.held += 1
            else:
                self.uploads.refused += 1
                self.reasons.extend(answer["reasons"])
        elif status == 410:
            outcome = "late"
            self.uploads.late += 1
        elif status == 409 and "already_answered" in str(answer):
            outcome = "answered before"  # by an earlier run of this agent: that answer stands
            self._stale = True  # which version bids next is read when the next round opens
        else:
            raise RemoteError(f"upload of round {info.round}: {status} {str(answer)[:500]}")
        entry = RoundLog(
            info.round, received, tuned_at - received, time.monotonic() - tuned_at, outcome
        )
        self.log.append(entry)
        return entry
