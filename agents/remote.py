"""Remote agents: participants that take part in auctions over HTTP and fine-tune their own Fish
Sale Negotiator in each remote fine-tuning round (paper, "Implicit augmentation": only the item
rows travel; the agent's own model makes the D_ic noisy copies).

``RemoteAgent`` is the Python API for one participant with one model: ``submit`` it, find or
join an auction, ``play`` it to the end. In each round the agent long-polls the round, runs its
``fine_tuner`` (any code: ``(current manifest, RoundInfo) -> fine-tuned manifest``) and uploads
the result with its token. ``faithful_fine_tune`` is what the server itself would do
(``agents.fine_tuning.fine_tune_round`` on the agent's model alone, with the round's seeds and the
patron's position), so a population of faithful agents replays the in-process auction.
``always_hold`` is the bait-and-switch of a saboteur: always-hold weights on the model it was
admitted with.

``run_population`` drives many agents from one asyncio loop (``srd agents``): honest agents
from the paper's randomisation, saboteurs that submit an honest-looking model and then upload
``always_hold``. Every request retries with exponential backoff on connection errors, 429 and
503 (honouring Retry-After) until ``give_up_s`` has passed, then ``ServerGoneError`` names the
server. Bytes of request and response bodies are counted, as the server counts them.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import re
import secrets
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import httpx
import numpy as np
import torch

from agents.batch import from_manifests, to_manifest
from agents.fine_tuning import fine_tune_round
from agents.manifest import Manifest
from agents.negotiator import honest_manifest, saboteur_manifest

MAX_AGENTS = 256
"""Honest plus saboteur agents of one population, at most."""
ROUND_WAIT_S = 25.0
"""Long-poll of one round request (the server allows up to 30 s)."""
HTTP_TIMEOUT_S = 20.0
"""Time allowed for one HTTP exchange (a long poll gets ROUND_WAIT_S more)."""
GIVE_UP_S = 60.0
"""A request that keeps failing is given up after this long."""
RETRY_FIRST_S, RETRY_MAX_S = 0.05, 2.0
"""Backoff between retries: doubling from the first delay up to the largest, with jitter."""
AUCTION_WAIT_S = 600.0
"""How long agents wait for an auction that contains their models."""
AUCTION_POLL_S = 0.5
"""How often they look for it."""
SUBMIT_CONCURRENCY = 16
"""Submissions in flight at once."""
RETRY_STATUSES = frozenset({429, 503})
ONE_CONNECTION = httpx.Limits(max_connections=1, max_keepalive_connections=1)
"""An agent's requests follow one another: one keep-alive connection each."""
NAME_PREFIX = r"[A-Za-z0-9_.\-]{1,48}"
"""Participant names are <prefix>-honest-000 and the like (64 characters at most in all)."""


class RemoteError(RuntimeError):
    """The server answered something the agent cannot go on with."""


class ServerGoneError(RemoteError):
    """The server did not answer within ``give_up_s`` (its URL is in the message)."""


@dataclass
class Traffic:
    """Bodies sent and received, in bytes, and how many requests (and retries) it took."""

    bytes_up: int = 0
    bytes_down: int = 0
    requests: int = 0
    retries: int = 0


class Client:
    """JSON over HTTP with retries and byte counting (into ``traffic``, which several clients
    may share). Give each agent its own client (one connection, as on its own machine): one
    httpx pool serving many agents' concurrent requests costs time quadratic in their number."""

    def __init__(
        self,
        http: httpx.AsyncClient,
        *,
        give_up_s: float = GIVE_UP_S,
        rng: random.Random | None = None,
        traffic: Traffic | None = None,
    ) -> None:
        self.http = http
        self.give_up_s = give_up_s
        self.traffic = traffic or Traffic()
        self._rng = rng or random.Random(0)

    @property
    def server(self) -> str:
        return str(self.http.base_url)

    async def request(
        self,
        method: str,
        path: str,
        *,
        body: bytes | None = None,
        token: str | None = None,
        timeout_s: float = HTTP_TIMEOUT_S,
        resend: bool = True,
    ) -> httpx.Response:
        """One request, retried on connection errors, 429 and 503 until ``give_up_s``. With
        ``resend=False`` a request that may have reached the server is not sent again (only
        connection failures before sending, 429 and 503 are retried)."""
        headers = {"Content-Type": "application/json"} if body is not None else {}
        if token is not None:
            headers["Authorization"] = f"Bearer {token}"
        give_up = time.monotonic() + self.give_up_s
        delay = RETRY_FIRST_S
        while True:
            self.traffic.requests += 1
            try:
                response = await self.http.request(
                    method, path, content=body, headers=headers, timeout=timeout_s
                )
            except httpx.TransportError as exc:
                unsent = isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout)
                if not (resend or unsent) or time.monotonic() + delay > give_up:
                    raise ServerGoneError(
                        f"the server at {self.server} did not answer {method} {path} "
                        f"({type(exc).__name__}: {exc}); gave up after {self.give_up_s:.0f} s"
                    ) from exc
                wait_s = delay
            else:
                self.traffic.bytes_up += len(body or b"")
                self.traffic.bytes_down += len(response.content)
                if response.status_code not in RETRY_STATUSES:
                    return response
                if time.monotonic() + delay > give_up:
                    raise ServerGoneError(
                        f"the server at {self.server} kept answering {response.status_code} "
                        f"to {method} {path}; gave up after {self.give_up_s:.0f} s"
                    )
                wait_s = _retry_after(response, delay)
            self.traffic.retries += 1
            await asyncio.sleep(wait_s * (0.5 + self._rng.random()))
            delay = min(delay * 2, RETRY_MAX_S)

    async def json(self, method: str, path: str, **kwargs: Any) -> Any:
        """``request`` that expects a 2xx JSON answer (else RemoteError with the server's)."""
        response = await self.request(method, path, **kwargs)
        if not response.is_success:
            raise RemoteError(f"{method} {path}: {response.status_code} {response.text[:500]}")
        return response.json()


def _retry_after(response: httpx.Response, default_s: float) -> float:
    with contextlib.suppress(ValueError):
        return max(default_s, float(response.headers.get("Retry-After", "")))
    return default_s


@dataclass(frozen=True)
class RoundInfo:
    """One fine-tuning round as the agent receives it."""

    auction_id: int
    round: int
    iteration: int
    rows: np.ndarray
    """(R, 8) float64: p, l, w, g, st1, st2, st3, f of every item row."""
    fine_tune_seed: int
    augmentation_seed: int
    deadline: datetime
    seconds_left: float
    position: int
    """The agent's patron position in the auction (its seeds depend on it)."""


FineTuner = Callable[[Manifest, RoundInfo], Manifest]
"""The participant's own fine-tuning: current manifest and round → the manifest to upload
(weights and biases may change, nothing else)."""


def faithful_fine_tune(manifest: Manifest, info: RoundInfo) -> Manifest:
    """SRD fine-tuning of this one model exactly as the server would run it: the manifest's
    own epochs, batch size and learning rate, the round's rows and seeds, the patron's
    position."""
    if manifest.fine_tuning.epochs == 0:
        return manifest
    tuned = fine_tune_round(
        from_manifests([manifest]),
        torch.from_numpy(info.rows),
        np.array([info.fine_tune_seed], dtype=np.uint64),
        np.array([info.augmentation_seed], dtype=np.uint64),
        np.array([info.position]),
    )
    return to_manifest(tuned, 0)


def always_hold(manifest: Manifest, info: RoundInfo) -> Manifest:
    """The bait-and-switch: the admitted model's design with a saboteur's always-hold weights
    and biases (buy neuron inert, hold bias +5), whatever the round says."""
    switched = saboteur_manifest(np.random.default_rng(info.round), manifest.participant)
    data = switched.model_dump(mode="json")
    kept = manifest.model_dump(mode="json")
    for name in ("participant", "description", "augmentation", "fine_tuning"):
        data[name] = kept[name]
    data["pfc"]["trainable"] = kept["pfc"]["trainable"]
    for name, neuron in data["external_sensor"].items():
        neuron["activation"] = kept["external_sensor"][name]["activation"]
    return Manifest.model_validate(data)


@dataclass
class RoundLog:
    """What one agent did in one round (times in seconds, monotonic clock)."""

    round: int
    received_at: float
    fine_tune_s: float
    upload_s: float
    outcome: str
    """accepted | refused | late | unanswered (not asked any more) | error."""


@dataclass
class Uploads:
    accepted: int = 0
    refused: int = 0
    late: int = 0


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
    ) -> None:
        self.client = client
        self.current = manifest
        """The version the server lets this patron bid with (updated on every acceptance)."""
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
        self.model_id = int(answer["model_id"])
        self.token = answer.get("token") or self.token
        self.accepted_at_submit = bool(answer["accepted"])
        return answer

    async def auctions(self) -> list[int]:
        """The auctions this agent's model entered, newest first."""
        model = await self.client.json("GET", f"/models/{self._id}")
        return [int(a) for a in model.get("auctions", [])]

    @property
    def _id(self) -> int:
        if self.model_id is None:
            raise RemoteError("the agent has no model id: submit first")
        return self.model_id

    async def play(
        self, auction_id: int, on_round: Callable[[RoundLog], None] | None = None
    ) -> None:
        """Answer every round of the auction this agent is asked in, until it ends (or the
        patron leaves it by buying or quitting)."""
        auction = await self.client.json("GET", f"/auctions/{auction_id}")
        if self._id not in auction["model_ids"]:
            raise RemoteError(f"model {self._id} is not a patron of auction {auction_id}")
        position = auction["model_ids"].index(self._id)
        after = 0
        while True:
            response = await self.client.request(
                "GET",
                f"/auctions/{auction_id}/rounds/current?wait={ROUND_WAIT_S}&after={after}",
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
            if self._id not in state["asked"]:
                return  # bought or quit: never asked again
            entry = await self._answer(auction_id, state, position, received)
            if on_round is not None:
                on_round(entry)

    async def _answer(
        self, auction_id: int, state: dict[str, Any], position: int, received: float
    ) -> RoundLog:
        info = RoundInfo(
            auction_id=auction_id,
            round=int(state["round"]),
            iteration=int(state["iteration"]),
            rows=np.array(state["rows"], dtype=np.float64),
            fine_tune_seed=int(state["fine_tune_seed"]),
            augmentation_seed=int(state["augmentation_seed"]),
            deadline=datetime.fromisoformat(state["deadline"]),
            seconds_left=float(state["seconds_left"]),
            position=position,
        )
        tuned = self.fine_tuner(self.current, info)
        tuned_at = time.monotonic()
        response = await self.client.request(
            "PUT",
            f"/auctions/{auction_id}/rounds/{info.round}/models/{self._id}",
            body=tuned.model_dump_json().encode(),
            token=self.token,
        )
        outcome = "error"
        if response.status_code == 200:
            answer = response.json()
            outcome = answer["outcome"]
            if answer["accepted"]:
                self.current = tuned
                self.uploads.accepted += 1
            else:
                self.uploads.refused += 1
                self.reasons.extend(answer["reasons"])
        elif response.status_code == 410:
            outcome = "late"
            self.uploads.late += 1
        else:
            raise RemoteError(
                f"upload of round {info.round}: {response.status_code} {response.text[:500]}"
            )
        entry = RoundLog(
            info.round, received, tuned_at - received, time.monotonic() - tuned_at, outcome
        )
        self.log.append(entry)
        return entry


# --- a population of agents (``srd agents``) --------------------------------------------------


@dataclass(frozen=True)
class PopulationConfig:
    """A population of remote agents and what they join."""

    server: str
    """Base URL of the auction house."""
    honest: int = 6
    """Honest agents (the paper's randomisation), faithful fine-tuners."""
    saboteurs: int = 0
    """Bait-and-switch agents: an honest-looking model, then always-hold uploads."""
    seed: int = 0
    """Seeds the population's models (same seed, same models)."""
    auction: int | None = None
    """Join this auction; None: wait for one containing the population's models (or create
    it with ``admin_token``)."""
    admin_token: str | None = None
    """Operator token: create a remote auction of the population's models."""
    rarity: float = 0.5
    """Supply of the created auction (fish = int(rarity × patrons))."""
    fine_tune_rounds: int = 4
    """Rounds of the created auction."""
    round_deadline_s: float = 10.0
    """Round deadline of the created auction."""
    auction_seed: int = 0
    """Seed of the created auction."""
    name_prefix: str | None = None
    """Participant names start with this (default: a fresh random tag)."""
    give_up_s: float = GIVE_UP_S
    """A request that keeps failing is given up after this long."""
    auction_wait_s: float = AUCTION_WAIT_S
    """How long to wait for an auction containing the population's models."""

    def __post_init__(self) -> None:
        problems = []
        if self.honest < 0 or self.saboteurs < 0:
            problems.append("honest and saboteurs must be ≥ 0")
        if not 1 <= self.honest + self.saboteurs <= MAX_AGENTS:
            problems.append(f"honest + saboteurs must be between 1 and {MAX_AGENTS}")
        if self.seed < 0:
            problems.append("seed must be ≥ 0")
        if self.name_prefix is not None and not re.fullmatch(NAME_PREFIX, self.name_prefix):
            problems.append(f"name_prefix must match {NAME_PREFIX} (a participant name's start)")
        if problems:
            raise ValueError("; ".join(problems))


@dataclass
class PopulationReport:
    """What a population did: the ``srd agents --json`` object."""

    server: str
    agents: int
    honest: int
    saboteurs: int
    model_ids: list[int]
    auctions: list[int]
    uploads: dict[str, int]
    bytes_up: int
    bytes_down: int
    requests: int
    retries: int
    rounds: int
    admitted: int
    """Models the screener accepted at submission."""
    refusal_rules: list[str]
    """The screener rules behind refused uploads (once each)."""
    auction: dict[str, Any] = field(default_factory=dict)
    """The final state of the auction: status, iterations, buyers, revenue, stop reason."""
    elapsed_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def population(config: PopulationConfig, clients: Sequence[Client]) -> list[RemoteAgent]:
    """The population's agents, one client each: honest ones first, then the saboteurs
    (honest-looking)."""
    rng = np.random.default_rng(config.seed)
    prefix = config.name_prefix or f"agents-{config.seed}-{secrets.token_hex(3)}"
    agents = []
    for i in range(config.honest + config.saboteurs):
        saboteur = i >= config.honest
        name = f"{prefix}-{'saboteur' if saboteur else 'honest'}-{i:03d}"
        agents.append(
            RemoteAgent(
                clients[i],
                honest_manifest(rng, name),
                fine_tuner=always_hold if saboteur else faithful_fine_tune,
            )
        )
    return agents


async def _gather_bounded(jobs: list[Awaitable[Any]], limit: int) -> list[Any]:
    gate = asyncio.Semaphore(limit)

    async def run(job: Awaitable[Any]) -> Any:
        async with gate:
            return await job

    return list(await asyncio.gather(*(run(job) for job in jobs)))


async def _find_auction(agents: list[RemoteAgent], wait_s: float) -> int:
    """The newest auction that one of the agents' models entered (waiting for it)."""
    give_up = time.monotonic() + wait_s
    while True:
        found = await agents[0].auctions()
        if found:
            return found[0]
        if time.monotonic() > give_up:
            raise RemoteError(f"no auction contains model {agents[0].model_id} after {wait_s} s")
        await asyncio.sleep(AUCTION_POLL_S)


async def _create_auction(config: PopulationConfig, client: Client, model_ids: list[int]) -> int:
    assert config.admin_token is not None
    body = {
        "rarity": config.rarity,
        "model_ids": model_ids,
        "fine_tune_mode": "remote",
        "fine_tune_rounds": config.fine_tune_rounds,
        "round_deadline_s": config.round_deadline_s,
        "seed": config.auction_seed,
    }
    answer = await client.json(
        "POST", "/auctions", body=json.dumps(body).encode(), token=config.admin_token
    )
    return int(answer["auction_id"])


Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: submitted agents, answered rounds."""


async def run_population(
    config: PopulationConfig, progress: Progress | None = None
) -> PopulationReport:
    """Register the population, join (or wait for, or create) its auction, answer every round,
    follow the auction to its end, and report."""
    started = time.monotonic()
    n_agents = config.honest + config.saboteurs
    traffic = Traffic()
    rng = random.Random(config.seed)
    async with contextlib.AsyncExitStack() as stack:
        clients = [
            Client(
                await stack.enter_async_context(
                    httpx.AsyncClient(base_url=config.server, limits=ONE_CONNECTION)
                ),
                give_up_s=config.give_up_s,
                rng=random.Random(rng.random()),
                traffic=traffic,
            )
            for _ in range(n_agents)
        ]
        client = clients[0]
        agents = population(config, clients)
        done = 0

        async def submit(agent: RemoteAgent) -> None:
            nonlocal done
            await agent.submit()
            done += 1
            if progress is not None:
                progress("submitted", done, n_agents)

        await _gather_bounded([submit(a) for a in agents], SUBMIT_CONCURRENCY)
        model_ids = [a._id for a in agents]
        if config.auction is not None:
            auction_id = config.auction
        elif config.admin_token is not None:
            auction_id = await _create_auction(config, client, model_ids)
        else:
            auction_id = await _find_auction(agents, config.auction_wait_s)
        answered = 0

        def on_round(_entry: RoundLog) -> None:
            nonlocal answered
            answered += 1
            if progress is not None:
                progress("answered", answered, n_agents * max(config.fine_tune_rounds, 1))

        await asyncio.gather(*(agent.play(auction_id, on_round) for agent in agents))
        final = await client.json("GET", f"/auctions/{auction_id}")
        while final["status"] in ("pending", "running"):
            await asyncio.sleep(AUCTION_POLL_S)
            final = await client.json("GET", f"/auctions/{auction_id}")
    uploads = Uploads(
        accepted=sum(a.uploads.accepted for a in agents),
        refused=sum(a.uploads.refused for a in agents),
        late=sum(a.uploads.late for a in agents),
    )
    return PopulationReport(
        server=config.server,
        agents=n_agents,
        honest=config.honest,
        saboteurs=config.saboteurs,
        model_ids=model_ids,
        auctions=[auction_id],
        uploads=dict(uploads.__dict__),
        bytes_up=traffic.bytes_up,
        bytes_down=traffic.bytes_down,
        requests=traffic.requests,
        retries=traffic.retries,
        rounds=len(final.get("fine_tuning", [])),
        admitted=sum(bool(a.accepted_at_submit) for a in agents),
        refusal_rules=sorted({r["rule"] for a in agents for r in a.reasons}),
        auction={
            "id": auction_id,
            "status": final["status"],
            "iterations": final["iteration"],
            "buyers": len(final["buyers"]),
            "revenue": final["revenue"],
            "stop_reason": final["stop_reason"],
            "error": final["error"],
        },
        elapsed_s=round(time.monotonic() - started, 3),
    )
