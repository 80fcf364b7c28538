"""Remote fine-tuning over loopback: traffic per round and the protocol's own time.

1. Bytes on the wire per fine-tuning round (request and response bodies: each asked agent's
   round answer as received, its upload and its answer as the server counts them): with
   implicit augmentation (the product: the round answer carries the 64 × 8 item
   rows and two seeds, each agent's model makes its own D_ic noisy copies) against an explicit
   variant where the server would ship every asked agent the augmented copies its fine-tuning
   visits (its epochs × rows × its D_ic copies × 8 numbers, and its row shuffles). The explicit
   answers exist in this benchmark only: they are built from the same draws the agent makes
   (``agents.fine_tuning.draw_fine_tune_seeded``) and serialised as the server serialises JSON.
   Uploads (the fine-tuned manifests) and their answers count in both.
2. Wall time of remote auctions of 64 agents over loopback when every agent answers, per round:
   publishing (the worker begins the iteration that opens the round: from round 2 on, the
   transaction that closes the round before, applies its versions, plays the iteration and
   commits it with the checkpoint → the last agent has the round; an auction's first round from
   the later of its opening and the agents' joining), the agents' own fine-tuning (each agent
   alone, as on its own machine, encoding its upload included; run here one after another and
   reported, not counted), upload (first upload sent → last answer, re-screening included),
   re-screening alone (the round's uploads through ``screener.rescreen_many`` in batches of 16,
   as the screening process judges them, timed in this process), and closing (last answer →
   the worker begins closing the round). The protocol's overhead is everything but the
   fine-tuning (no target: the server's budgets per upload are ``benchmarks/capacity.py``'s).
   Agents leave as they buy or quit, so later rounds ask fewer of them: the medians are over
   all rounds, and again over the rounds that ask at least three quarters of the agents.
3. CPU per round: the server's processes' (read from ``/proc``, at the kernel's 10 ms tick) and
   this driver's, in the same phases, fitted against the agents asked (fixed + per agent, over
   rounds 2 on, whose CPU window is one whole cycle), for the server and its agents together
   and for the server alone. The agents here share the server's cores, so no round can take
   less than its CPU divided by the cores: the benchmark prints that floor for a round of all
   the agents, and how far above it the measured rounds are.

The agents here are driven in phases (all receive, all fine-tune, all upload at once) so that
the phases can be timed apart; ``srd agents`` interleaves them per agent. ``--transport
websocket`` plays the same rounds over one round socket per agent (``agents.remote.RoundSocket``)
instead of a long poll and a PUT per agent and round.

Run: ``.venv/bin/python benchmarks/remote_traffic.py [--agents 64] [--auctions 3]
[--postgres] [--no-access-log] [--transport http|websocket]``
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import secrets
import statistics
import sys
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.batch import from_manifests
from agents.fine_tuning import derive_seeds, draw_fine_tune_seeded
from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from agents.remote import ONE_CONNECTION, Client, RoundInfo, RoundSocket, faithful_fine_tune
from screener import rescreen_many
from server.cli.launch import ServerProcess, settings_environment
from server.screening.pool import MAX_BATCH
from tests.support.databases import postgres_admin_url, throwaway_postgres
from tests.support.processes import cpu_seconds, descendants
from tests.support.server import QUOTAS_OFF

torch.set_num_threads(1)
ADMIN_TOKEN = secrets.token_hex(16)
RARITY = 0.1
"""Few fish, so demand stays high and the auction reaches its fine-tuning rounds."""
ROUND_DEADLINE_S = 60.0
"""Long: in this benchmark every round closes at its last upload."""
WAIT_S = 25.0


@dataclass
class RoundTiming:
    """One round's phases, in seconds."""

    auction: int
    round: int
    agents: int
    publish: float
    fine_tune_sum: float
    fine_tune_max: float
    upload: float
    rescreen: float
    close: float
    bytes_implicit: int
    bytes_explicit: int
    cpu: Cpu
    """Used during the HTTP phases (close, publish and upload), fine-tuning left out."""

    @property
    def overhead(self) -> float:
        """Everything but the agents' fine-tuning."""
        return self.publish + self.upload + self.close


class ServerTree:
    """The server's processes (the API, its screening process, its workers), found by one scan
    of ``/proc`` when asked (``refresh``): reading their CPU then reads only their own ``stat``
    files, so measuring never scans ``/proc`` between the phases it measures."""

    def __init__(self, root: int) -> None:
        self.root = root
        self.pids = descendants(root)

    def refresh(self) -> None:
        self.pids = descendants(self.root)

    def cpu(self) -> float:
        """CPU seconds used so far by the processes found."""
        return sum(cpu_seconds(pid) or 0.0 for pid in self.pids)


@dataclass
class Cpu:
    """CPU seconds of the server (its whole process tree) and of this driver process."""

    server: float
    driver: float

    @classmethod
    def now(cls, tree: ServerTree) -> Cpu:
        return cls(tree.cpu(), time.process_time())

    def __sub__(self, other: Cpu) -> Cpu:
        return Cpu(self.server - other.server, self.driver - other.driver)

    def __add__(self, other: Cpu) -> Cpu:
        return Cpu(self.server + other.server, self.driver + other.driver)

    @property
    def total(self) -> float:
        """The server's and the agents' CPU: what the machine's cores must do in the round."""
        return self.server + self.driver


def stamp(text: str) -> float:
    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def explicit_answer_bytes(state: dict[str, Any], manifest: Manifest, position: int) -> int:
    """The JSON body an explicit-augmentation server would send this agent instead of the
    rows and seeds: the round's head plus, for every epoch, the agent's row shuffle and the
    D_ic augmented copies of every row (nothing to ship for an agent without epochs)."""
    head = {
        k: v for k, v in state.items() if k not in ("rows", "fine_tune_seed", "augmentation_seed")
    }
    epochs, copies = manifest.fine_tuning.epochs, manifest.augmentation.copies
    shuffles: list[Any] = []
    augmented: list[Any] = []
    if epochs:
        rows = torch.tensor(state["rows"], dtype=torch.float64)
        draws = draw_fine_tune_seeded(
            from_manifests([manifest]),
            rows.shape[0],
            derive_seeds(state["fine_tune_seed"], [position]),
            derive_seeds(state["augmentation_seed"], [position]),
        )
        shuffles = draws.order[0, :epochs].tolist()
        augmented = (rows[None, :, None, :] + draws.noise[0, :epochs, :, :copies]).tolist()
    body = {**head, "shuffles": shuffles, "augmented_rows": augmented}
    return len(json.dumps(body, separators=(",", ":")).encode())


@dataclass
class Agent:
    client: Client
    """Its own connection (as on its own machine)."""
    model_id: int
    token: str
    position: int
    current: Manifest
    socket: RoundSocket | None = None
    """Its round socket to the auction being played (``--transport websocket``)."""


async def receive(agent: Agent, path: str, after: int, received: list[float]) -> dict[str, Any]:
    """One agent's long poll (or its socket's next round); notes when the round arrived."""
    if agent.socket is not None:
        state = await agent.socket.next_round(after)
    else:
        response = await agent.client.request("GET", path, timeout_s=WAIT_S + 10)
        state = response.json()
    received.append(time.time())
    return dict(state)


async def upload(auction_id: int, round_number: int, agent: Agent, body: bytes) -> Any:
    if agent.socket is not None:
        status, answer = await agent.socket.upload(round_number, agent.model_id, body)
        assert status == 200, answer
        return answer
    response = await agent.client.request(
        "PUT",
        f"/auctions/{auction_id}/rounds/{round_number}/models/{agent.model_id}",
        body=body,
        token=agent.token,
    )
    assert response.status_code == 200, response.text
    return response.json()


@dataclass
class Played:
    """What the driver saw of one round (times: wall-clock seconds)."""

    state: dict[str, Any]
    received: list[float]
    fine_tune: list[float]
    sent: float
    answered: float
    before: list[tuple[int, Manifest]]
    """(position, manifest it fine-tuned from) of every asked agent."""
    changed: list[Manifest]
    cpu: Cpu
    ready: float = 0.0
    """When the agents could first be reached (an auction's first round only: its sockets
    connected, or its first long polls sent; the agents join once the auction exists, often
    after its first round has opened): that round's publishing is timed from the later of
    this and the round's opening."""


async def play_auction(
    client: Client, agents: list[Agent], auction_id: int, tree: ServerTree, transport: str
) -> list[RoundTiming]:
    """Answer every round of the auction with all its active agents, phase by phase (the next
    long polls go out as soon as the uploads are answered, as real agents do); the phases and
    the bytes are worked out once the auction has ended."""
    async with contextlib.AsyncExitStack() as sockets:
        if transport == "websocket":
            opened = [RoundSocket(a.client.server, auction_id, a.token) for a in agents]
            await asyncio.gather(*(sockets.enter_async_context(o) for o in opened))
            for agent, socket in zip(agents, opened, strict=True):
                agent.socket = socket
        ready = time.time()
        played = await play_rounds(agents, auction_id, tree)
    if played:
        played[0].ready = ready
    return await timings_of(client, auction_id, played)


async def play_rounds(agents: list[Agent], auction_id: int, tree: ServerTree) -> list[Played]:
    """Every round of the auction, phase by phase, as the driver saw it."""
    played: list[Played] = []
    active = list(agents)
    after = 0
    mark = Cpu.now(tree)
    while active:
        path = f"/auctions/{auction_id}/rounds/current?wait={WAIT_S}&after={after}"
        received: list[float] = []
        state = (await asyncio.gather(*(receive(a, path, after, received) for a in active)))[0]
        published = Cpu.now(tree) - mark
        if not played:  # this auction's worker is running now: find it, between two phases
            tree.refresh()
        if state["auction_status"] not in ("pending", "running") or state["status"] != "open":
            break
        for gone in (a for a in active if a.model_id not in state["asked"]):
            if gone.socket is not None:  # bought or quit: it leaves, as RemoteAgent does
                await gone.socket.close()
        active = [a for a in active if a.model_id in state["asked"]]
        before = [(a.position, a.current) for a in active]
        tuned, bodies, costs = [], [], []
        for agent in active:  # each agent's own work: fine-tune, encode the upload
            started = time.perf_counter()
            tuned.append(
                faithful_fine_tune(agent.current, RoundInfo.from_state(state, agent.position))
            )
            bodies.append(tuned[-1].model_dump_json().encode())
            costs.append(time.perf_counter() - started)
        before_upload = Cpu.now(tree)
        sent = time.time()
        answers = await asyncio.gather(
            *(upload(auction_id, state["round"], a, b) for a, b in zip(active, bodies, strict=True))
        )
        answered = time.time()
        mark = Cpu.now(tree)
        cpu = published + (mark - before_upload)
        for agent, manifest, answer in zip(active, tuned, answers, strict=True):
            if answer["accepted"]:
                agent.current = manifest
        changed = [m for m, (_, b) in zip(tuned, before, strict=True) if m != b]
        played.append(Played(state, received, costs, sent, answered, before, changed, cpu))
        after = state["round"]
    return played


async def timings_of(client: Client, auction_id: int, played: list[Played]) -> list[RoundTiming]:
    """Each played round's phases, from the driver's clock and the auction's record."""
    auction = await client.json("GET", f"/auctions/{auction_id}")
    rounds = {r["round"]: r for r in auction["fine_tuning"]}
    timings = []
    for p in played:
        closing = rounds[p.state["round"]]
        opened_at, closed_at = stamp(closing["opened_at"]), stamp(closing["closed_at"])
        started = time.perf_counter()
        for first in range(0, len(p.changed), MAX_BATCH):
            rescreen_many(p.changed[first : first + MAX_BATCH])
        rescreen = time.perf_counter() - started
        uploads = sum(a["bytes_in"] + a["bytes_out"] for a in closing["answers"])
        explicit = sum(explicit_answer_bytes(p.state, m, position) for position, m in p.before)
        implicit = len(p.before) * len(json.dumps(p.state, separators=(",", ":")).encode())
        timings.append(
            RoundTiming(
                auction=auction_id,
                round=p.state["round"],
                agents=len(p.before),
                publish=max(p.received) - max(opened_at, p.ready),
                fine_tune_sum=sum(p.fine_tune),
                fine_tune_max=max(p.fine_tune),
                upload=p.answered - p.sent,
                rescreen=rescreen,
                close=closed_at - p.answered,
                bytes_implicit=implicit + uploads,
                bytes_explicit=explicit + uploads,
                cpu=p.cpu,
            )
        )
    return timings


async def run(
    server: ServerProcess, n_agents: int, n_auctions: int, transport: str
) -> list[RoundTiming]:
    assert server.process is not None
    tree = ServerTree(server.process.pid)
    async with contextlib.AsyncExitStack() as stack:
        clients = [
            Client(
                await stack.enter_async_context(
                    httpx.AsyncClient(base_url=server.url, limits=ONE_CONNECTION)
                )
            )
            for _ in range(n_agents)
        ]
        timings: list[RoundTiming] = []
        for k in range(n_auctions):
            rng = np.random.default_rng(1000 + k)
            tag = secrets.token_hex(3)
            agents: list[Agent] = []
            drawn = 0
            while len(agents) < n_agents:  # the screener refuses a few honest draws
                lacking = n_agents - len(agents)
                manifests = [
                    honest_manifest(rng, f"bench-{tag}-{drawn + i:03d}") for i in range(lacking)
                ]
                drawn += lacking
                free = clients[len(agents) :]
                submitted = await asyncio.gather(
                    *(
                        c.json("POST", "/submit", body=m.model_dump_json().encode())
                        for c, m in zip(free, manifests, strict=True)
                    )
                )
                agents += [
                    Agent(c, s["model_id"], s["token"], 0, m)
                    for c, s, m in zip(free, submitted, manifests, strict=True)
                    if s["accepted"]
                ]
            for position, agent in enumerate(agents):
                agent.position = position
            body = {
                "rarity": RARITY,
                "model_ids": [a.model_id for a in agents],
                "fine_tune_mode": "remote",
                "round_deadline_s": ROUND_DEADLINE_S,
                "seed": k,
            }
            created = await clients[0].json(
                "POST", "/auctions", body=json.dumps(body).encode(), token=ADMIN_TOKEN
            )
            timings += await play_auction(
                clients[0], agents, created["auction_id"], tree, transport
            )
        return timings


def median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def report(timings: list[RoundTiming], n_agents: int) -> None:
    print("\nper round (ms; agents asked; bytes with implicit vs explicit augmentation)")
    print(
        f"{'auction':>7} {'round':>5} {'agents':>6} {'publish':>8} {'upload':>8} {'rescreen':>8} "
        f"{'close':>7} {'overhead':>8} {'CPU':>6} {'tune sum':>8} {'implicit B':>10} "
        f"{'explicit B':>11} {'ratio':>6}"
    )
    for t in timings:
        print(
            f"{t.auction:>7} {t.round:>5} {t.agents:>6} {t.publish * 1e3:8.1f} "
            f"{t.upload * 1e3:8.1f} {t.rescreen * 1e3:8.1f} {t.close * 1e3:7.1f} "
            f"{t.overhead * 1e3:8.1f} {t.cpu.total * 1e3:6.0f} {t.fine_tune_sum * 1e3:8.1f} "
            f"{t.bytes_implicit:>10} "
            f"{t.bytes_explicit:>11} {t.bytes_explicit / t.bytes_implicit:6.1f}"
        )
    following = [t for t in timings if t.round > 1]  # their CPU window is one whole cycle
    full = [t for t in timings if 4 * t.agents >= 3 * n_agents]
    print(f"\nmedians over {len(timings)} rounds ({n_agents} agents per auction):")
    for name, values in (
        ("publishing", [t.publish for t in timings]),
        ("upload (re-screening included)", [t.upload for t in timings]),
        ("re-screening alone (in this process)", [t.rescreen for t in timings]),
        ("closing (last answer → the worker closes)", [t.close for t in timings]),
        ("protocol overhead", [t.overhead for t in timings]),
        ("  of which not re-screening", [t.overhead - t.rescreen for t in timings]),
        ("  over the rounds asking ≥ 3/4 of them", [t.overhead for t in full]),
        ("server CPU per round (rounds 2 on)", [t.cpu.server for t in following]),
        ("  driver CPU in the same phases", [t.cpu.driver for t in following]),
        ("agents' fine-tuning, summed", [t.fine_tune_sum for t in timings]),
        ("agents' fine-tuning, slowest agent", [t.fine_tune_max for t in timings]),
    ):
        print(f"  {name:<40} {median(values) * 1e3:8.1f} ms")
    cores = len(os.sched_getaffinity(0))
    if len({t.agents for t in following}) > 1:
        # A round's CPU ≈ fixed + per agent × agents asked (rounds 2 on: whole cycles).
        asked = [t.agents for t in following]
        for name, used in (
            ("server and agents", [t.cpu.total for t in following]),
            ("server alone", [t.cpu.server for t in following]),
        ):
            per_agent, fixed = np.polyfit(asked, used, 1)
            full_round = fixed + per_agent * n_agents
            print(
                f"  {'CPU per round, ' + name:<40} {fixed * 1e3:8.1f} ms + {per_agent * 1e3:.2f}"
                f" ms per agent asked (fit over {len(following)} rounds); a round of all"
                f" {n_agents} takes ≥ {full_round / cores * 1e3:.1f} ms on {cores} cores"
            )
        ratio = median([t.overhead / (t.cpu.total / cores) for t in following if t.cpu.total > 0])
        print(f"  {'overhead / (CPU ÷ cores), rounds 2 on':<40} {ratio:8.2f}")
    implicit = median([float(t.bytes_implicit) for t in timings])
    explicit = median([float(t.bytes_explicit) for t in timings])
    print(
        f"  {'bytes per round, implicit augmentation':<40} {implicit:8.0f}"
        f"\n  {'bytes per round, explicit augmentation':<40} {explicit:8.0f}"
        f"  ({explicit / implicit:.1f}× implicit; uploads counted in both)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=64, help="agents per auction")
    parser.add_argument("--auctions", type=int, default=3, help="auctions played one by one")
    parser.add_argument("--postgres", action="store_true", help="PostgreSQL instead of SQLite")
    parser.add_argument(
        "--no-access-log", action="store_true", help="serve with SRD_ACCESS_LOG=false"
    )
    parser.add_argument(
        "--transport",
        choices=("http", "websocket"),
        default="http",
        help="rounds by long poll and PUT, or over one round socket per agent",
    )
    args = parser.parse_args()
    with ExitStack() as stack:
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        url = f"sqlite:///{folder / 'srd.db'}"
        if args.postgres:
            admin_url = postgres_admin_url()
            if admin_url is None:
                raise SystemExit("PostgreSQL is not reachable on 127.0.0.1:5432")
            url = stack.enter_context(throwaway_postgres(admin_url))
        server = ServerProcess(
            database_url=url,
            data_dir=folder / "data",
            admin_token=ADMIN_TOKEN,
            # hundreds of agents from one address
            extra_env=settings_environment({**QUOTAS_OFF, "access_log": not args.no_access_log}),
        )
        stack.enter_context(server)
        backend = "PostgreSQL" if args.postgres else "SQLite"
        print(
            f"srd serve on {server.url} ({backend}); {args.auctions} auctions of {args.agents}"
            f" agents over {args.transport}"
        )
        timings = asyncio.run(run(server, args.agents, args.auctions, args.transport))
    report(timings, args.agents)


if __name__ == "__main__":
    main()
