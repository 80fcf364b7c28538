"""A population of remote agents (``srd agents``), driven from one asyncio loop: honest agents
from the paper's randomisation, saboteurs that submit an honest-looking model and then upload
``always_hold``; they join (or wait for, or create) an auction, answer every round, and report
what they did (``PopulationReport``)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import random
import re
import secrets
import tempfile
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from agents.negotiator import honest_manifest
from agents.remote.agent import TRANSPORTS, RemoteAgent, RoundLog, Transport, Uploads
from agents.remote.client import GIVE_UP_S, ONE_CONNECTION, Client, RemoteError, Traffic
from agents.remote.fine_tuners import always_hold, faithful_fine_tune

MAX_AGENTS = 256
"""Honest plus saboteur agents of one population, at most."""
AUCTION_WAIT_S = 600.0
"""How long agents wait for an auction that contains their models."""
AUCTION_POLL_S = 0.5
"""How often they look for it."""
SUBMIT_CONCURRENCY = 16
"""Submissions in flight at once."""
NAME_PREFIX = r"[A-Za-z0-9_.\-]{1,48}"
"""Participant names are <prefix>-honest-000 and the like (64 characters at most in all)."""
TOKEN = r"[\x21-\x7e]{1,4096}"
"""A bearer token as it can travel in an HTTP header: printable ASCII, no white space."""


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
    """An enrolling auction (created with ``enrollment_s``) that the population's accepted
    models join; checked before anything is registered. None: wait for one containing the
    population's models (or create it with ``admin_token``)."""
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
    transport: Transport = "http"
    """How the rounds travel: a long poll and a PUT per round, or one round socket per agent."""
    tokens_file: Path | None = None
    """Where each agent's participant, model id and token are written (mode 0600) once the
    population is registered, for the participants to go on without this run."""

    def __post_init__(self) -> None:
        problems = []
        if self.honest < 0 or self.saboteurs < 0:
            problems.append("honest and saboteurs must be ≥ 0")
        if not 1 <= self.honest + self.saboteurs <= MAX_AGENTS:
            problems.append(f"honest + saboteurs must be between 1 and {MAX_AGENTS}")
        if self.seed < 0:
            problems.append("seed must be ≥ 0")
        if self.transport not in TRANSPORTS:
            problems.append(f"transport must be one of {', '.join(TRANSPORTS)}")
        if self.name_prefix is not None and not re.fullmatch(NAME_PREFIX, self.name_prefix):
            problems.append(f"name_prefix must match {NAME_PREFIX} (a participant name's start)")
        for name in ("rarity", "round_deadline_s", "give_up_s", "auction_wait_s"):
            if not math.isfinite(getattr(self, name)):
                problems.append(f"{name} must be a finite number")
        if self.admin_token is not None and not re.fullmatch(TOKEN, self.admin_token):
            problems.append(
                "admin_token must be printable ASCII without white space (it travels in an "
                "HTTP header)"
            )
        agents = self.honest + self.saboteurs
        creates = self.admin_token is not None and self.auction is None
        if creates and math.isfinite(self.rarity) and int(self.rarity * agents) < 1:
            problems.append(
                f"rarity × agents must give at least one fish: int({self.rarity:g} × {agents}) is 0"
            )
        if self.tokens_file is not None:
            problem = _unwritable(self.tokens_file)
            if problem is not None:
                problems.append(f"tokens_file {problem}")
        if problems:
            raise ValueError("; ".join(problems))


def _unwritable(path: Path) -> str | None:
    """Why a new file cannot be written at ``path``, or None."""
    folder = path.parent
    if path.is_dir():
        return f"{path} is a folder"
    if not folder.is_dir():
        return f"{path}: no such folder {folder}"
    try:  # tried, not guessed from mode bits (a read-only mount refuses even root)
        with tempfile.TemporaryFile(dir=folder):
            return None
    except OSError as exc:
        return f"{path}: cannot write into the folder {folder}: {exc.strerror or exc}"


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
    transport: Transport = "http"
    """How the rounds travelled (``PopulationConfig.transport``)."""
    per_agent: list[dict[str, Any]] = field(default_factory=list)
    """One row per agent: participant, model id, its /submit status (accepted, refused or
    held), uploads by answer (and the rounds it was asked in and did not answer: ``missing``),
    the version it bid with last, what it did in the auction (``result``: ``bought`` with
    ``price``, ``quit``, ``stayed``, or ``out``: it did not play), bytes up and down, and the
    error that stopped it, if one did (the others play on)."""
    errors: int = 0
    """Agents stopped by an error (each row says which)."""

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
                transport=config.transport,
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


@dataclass
class SoFar:
    """What a population run has made so far, for a report when it is stopped midway."""

    agents: list[RemoteAgent] = field(default_factory=list)
    auction: int | None = None
    tokens_saved: bool = False
    """This run wrote its agents' tokens to ``PopulationConfig.tokens_file``."""

    def to_dict(self) -> dict[str, Any]:
        """The finished run's object as far as it got (``agents`` the count registered,
        ``model_ids``, ``auctions``, ``uploads``, the bytes), and ``registered``: each
        registered model's participant and id."""
        registered = [a for a in self.agents if a.model_id is not None]
        return {
            "agents": len(registered),
            "registered": [
                {"participant": a.current.participant, "model_id": a.model_id} for a in registered
            ],
            "model_ids": [a.model_id for a in registered],
            "auctions": [] if self.auction is None else [self.auction],
            "uploads": {
                outcome: sum(getattr(a.uploads, outcome) for a in self.agents)
                for outcome in ("accepted", "refused", "late", "held")
            },
            "bytes_up": sum(a.client.traffic.bytes_up for a in self.agents),
            "bytes_down": sum(a.client.traffic.bytes_down for a in self.agents),
        }


async def run_population(
    config: PopulationConfig, progress: Progress | None = None, so_far: SoFar | None = None
) -> PopulationReport:
    """Register the population, join (or wait for, or create) its auction, answer every round,
    follow the auction to its end, and report. ``so_far`` is kept up to date meanwhile (the
    agents as they register, the auction once known)."""
    started = time.monotonic()
    so_far = SoFar() if so_far is None else so_far
    async with contextlib.AsyncExitStack() as stack:
        clients = await _clients(config, stack)
        if config.auction is not None:
            await _require_enrolling(clients[0], config.auction)
        elif config.admin_token is not None:
            await _require_operator(clients[0], config.admin_token)
        agents = population(config, clients)
        so_far.agents = agents
        submitted = await _submit(agents, progress)
        if config.tokens_file is not None:
            save_tokens(config.tokens_file, agents)
            so_far.tokens_saved = True
        if config.auction is not None:
            so_far.auction = config.auction
            auction_id, players = config.auction, await _join(agents, config.auction)
        else:
            players = _admitted(agents)
            auction_id = await _auction(config, clients[0], players)
            so_far.auction = auction_id
        await _play(config, players, auction_id, progress)
        final = await _final(clients[0], auction_id)
    return _report(config, agents, submitted, auction_id, final, started)


def save_tokens(path: Path, agents: Sequence[RemoteAgent]) -> None:
    """Each agent's participant, model id and token, as JSON, in a file only its owner may read
    (created so: the tokens are never readable by others, not even for an instant)."""
    rows = [
        {"participant": a.current.participant, "model_id": a.model_id, "token": a.token}
        for a in agents
    ]
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as handle:
        json.dump(rows, handle, indent=1)
        handle.write("\n")


async def _clients(config: PopulationConfig, stack: contextlib.AsyncExitStack) -> list[Client]:
    """One client per agent (one connection each, its own traffic count), closed with
    ``stack``."""
    rng = random.Random(config.seed)
    return [
        Client(
            await stack.enter_async_context(
                httpx.AsyncClient(base_url=config.server, limits=ONE_CONNECTION)
            ),
            give_up_s=config.give_up_s,
            rng=random.Random(rng.random()),
            traffic=Traffic(),
        )
        for _ in range(config.honest + config.saboteurs)
    ]


async def _submit(agents: list[RemoteAgent], progress: Progress | None) -> list[dict[str, Any]]:
    """Submit every agent's model, ``SUBMIT_CONCURRENCY`` at a time; the answers, in order."""
    done = 0

    async def submit(agent: RemoteAgent) -> dict[str, Any]:
        nonlocal done
        answer = await agent.submit()
        done += 1
        if progress is not None:
            progress("submitted", done, len(agents))
        return answer

    return await _gather_bounded([submit(a) for a in agents], SUBMIT_CONCURRENCY)


async def _require_enrolling(client: Client, auction_id: int) -> None:
    """The named auction takes patrons now (it was created with ``enrollment_s`` and enrolls
    still): said before anything is registered."""
    response = await client.request("GET", f"/auctions/{auction_id}")
    if response.status_code == 404:
        raise RemoteError(f"auction {auction_id} does not exist on {client.server}")
    if not response.is_success:
        raise RemoteError(
            f"GET /auctions/{auction_id}: {response.status_code} {response.text[:500]}"
        )
    auction = response.json()
    if auction["status"] != "pending" or auction.get("enroll_until") is None:
        raise RemoteError(
            f"auction {auction_id} ({auction['status']}) takes no patrons: agents join only an "
            "auction created with enrollment_s while it enrolls (pending). Create one with "
            "enrollment_s, or start the agents first and create the auction from their models "
            "(they wait for it, --wait), or give --admin-token for them to create it"
        )


async def _require_operator(client: Client, admin_token: str) -> None:
    """The admin token is the server's operator token (it will create the auction): said
    before anything is registered, so that a wrong one leaves no participants behind."""
    response = await client.request("GET", "/reviews", token=admin_token)
    if response.status_code in (401, 403):
        raise RemoteError(
            f"the admin token is not the operator token of {client.server} "
            f"({response.status_code}); nothing was registered"
        )
    if not response.is_success:
        raise RemoteError(f"GET /reviews: {response.status_code} {response.text[:500]}")


async def _join(agents: list[RemoteAgent], auction_id: int) -> list[RemoteAgent]:
    """Every agent whose model was accepted joins the auction; those that did (the others
    came after its enrollment ended, or their model was not accepted: they stay out)."""

    async def join(agent: RemoteAgent) -> bool:
        if not agent.accepted_at_submit:
            return False
        body = json.dumps({"model_id": agent.submitted_id}).encode()
        path = f"/auctions/{auction_id}/patrons"
        response = await agent.client.request("POST", path, body=body, token=agent.token)
        if response.status_code == 409:  # the enrollment ended meanwhile
            return False
        if not response.is_success:
            raise RemoteError(f"POST {path}: {response.status_code} {response.text[:500]}")
        return True

    joined = await _gather_bounded([join(agent) for agent in agents], SUBMIT_CONCURRENCY)
    players = [agent for agent, ok in zip(agents, joined, strict=True) if ok]
    if not players:
        raise RemoteError(
            f"no agent could join auction {auction_id}: its enrollment ended "
            "before any accepted model joined (give it a longer enrollment_s)"
        )
    return players


def _admitted(agents: list[RemoteAgent]) -> list[RemoteAgent]:
    """The agents whose model the screener accepted at ``/submit``: they play; the refused and
    the held stay out (an auction takes accepted models only), and the report says so."""
    admitted = [agent for agent in agents if agent.accepted_at_submit]
    if not admitted:
        raise RemoteError(f"the screener accepted none of the {len(agents)} agents' models")
    return admitted


async def _auction(config: PopulationConfig, client: Client, agents: list[RemoteAgent]) -> int:
    """The auction the population plays: the configured one, a new one (with the admin
    token), or the newest one its models entered."""
    if config.admin_token is not None:
        return await _create_auction(config, client, [a.submitted_id for a in agents])
    return await _find_auction(agents, config.auction_wait_s)


async def _play(
    config: PopulationConfig,
    agents: list[RemoteAgent],
    auction_id: int,
    progress: Progress | None,
) -> None:
    """Every agent plays the auction to its end."""
    answered = 0

    def on_round(_entry: RoundLog) -> None:
        nonlocal answered
        answered += 1
        if progress is not None:
            progress("answered", answered, len(agents) * max(config.fine_tune_rounds, 1))

    ended = await asyncio.gather(
        *(agent.play(auction_id, on_round) for agent in agents), return_exceptions=True
    )
    for agent, outcome in zip(agents, ended, strict=True):
        if isinstance(outcome, RemoteError):  # this agent stops; the others played on
            agent.error = str(outcome)
        elif isinstance(outcome, BaseException):
            raise outcome


async def _final(client: Client, auction_id: int) -> dict[str, Any]:
    """The auction once it has ended."""
    final: dict[str, Any] = await client.json("GET", f"/auctions/{auction_id}")
    while final["status"] in ("pending", "running"):
        await asyncio.sleep(AUCTION_POLL_S)
        final = await client.json("GET", f"/auctions/{auction_id}")
    return final


def _last_versions(final: dict[str, Any]) -> dict[int, int]:
    """Patron model id → the version it bid with last (the auction's current version, whose
    number a round's answer gave)."""
    numbers = {
        answer["version_id"]: answer["version"]
        for fine_tuning_round in final.get("fine_tuning", [])
        for answer in fine_tuning_round["answers"]
    }
    current = final.get("current_model_ids") or final["model_ids"]
    return {
        patron: numbers[bidding]
        for patron, bidding in zip(final["model_ids"], current, strict=True)
        if bidding in numbers
    }


def _result(final: dict[str, Any], model_id: int) -> dict[str, Any]:
    """What the patron ``model_id`` did in the auction ``final``."""
    if model_id not in final["model_ids"]:
        return {"result": "out"}
    for buyer in final["buyers"]:
        if buyer["model_id"] == model_id:
            return {"result": "bought", "price": buyer["price"]}
    if model_id in final["quitters"]:
        return {"result": "quit"}
    # still in when it ended: to its end (finished), or stopped by a cancel or a failure, as
    # GET /participants/{name} words it
    return {"result": "stayed" if final["status"] == "finished" else "stopped"}


def _missing(final: dict[str, Any], model_id: int) -> int:
    """Rounds the patron was asked in and did not answer."""
    return sum(
        answer["model_id"] == model_id and answer["outcome"] == "missing"
        for fine_tuning_round in final.get("fine_tuning", [])
        for answer in fine_tuning_round["answers"]
    )


def _report(
    config: PopulationConfig,
    agents: list[RemoteAgent],
    submitted: list[dict[str, Any]],
    auction_id: int,
    final: dict[str, Any],
    started: float,
) -> PopulationReport:
    """What the population did in the auction ``final``, since ``started`` (monotonic)."""
    uploads = Uploads(
        accepted=sum(a.uploads.accepted for a in agents),
        refused=sum(a.uploads.refused for a in agents),
        late=sum(a.uploads.late for a in agents),
        held=sum(a.uploads.held for a in agents),
    )
    traffic = Traffic(
        bytes_up=sum(a.client.traffic.bytes_up for a in agents),
        bytes_down=sum(a.client.traffic.bytes_down for a in agents),
        requests=sum(a.client.traffic.requests for a in agents),
        retries=sum(a.client.traffic.retries for a in agents),
    )
    versions = _last_versions(final)
    per_agent = [
        {
            "participant": answer["participant"],
            "model_id": agent.submitted_id,
            "submitted": answer.get("status") or ("accepted" if answer["accepted"] else "refused"),
            "uploads": {
                **agent.uploads.__dict__,
                "missing": _missing(final, agent.submitted_id),
            },
            "version": versions.get(agent.submitted_id, answer["version"]),
            **_result(final, agent.submitted_id),
            "bytes_up": agent.client.traffic.bytes_up,
            "bytes_down": agent.client.traffic.bytes_down,
            **({"error": agent.error} if agent.error else {}),
        }
        for agent, answer in zip(agents, submitted, strict=True)
    ]
    return PopulationReport(
        server=config.server,
        agents=len(agents),
        honest=config.honest,
        saboteurs=config.saboteurs,
        model_ids=[a.submitted_id for a in agents],
        auctions=[auction_id],
        uploads=dict(uploads.__dict__),
        bytes_up=traffic.bytes_up,
        bytes_down=traffic.bytes_down,
        requests=traffic.requests,
        retries=traffic.retries,
        transport=config.transport,
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
        per_agent=per_agent,
        errors=sum(bool(a.error) for a in agents),
    )
