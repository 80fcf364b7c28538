"""Capacity of one ``srd serve`` under remote fine-tuning rounds: a replay load generator.

Agents take part in remote auctions (64 agents per auction; fewer only below 64) over either
transport: round sockets (``WS /auctions/{id}/rounds/socket``) or long poll + PUT
(``GET .../rounds/current?wait=`` and ``PUT .../rounds/{r}/models/{id}``). Each agent answers
each round it is asked in after a think time drawn from ``--think`` (default 1-5 s, standing
for its own fine-tuning elsewhere) with a PRE-BUILT upload: its submitted manifest with the
decision layer's biases moved by ``UPLOAD_STEP`` × the round, built before the run. The
upload is a real new version (re-screened, accepted by the screener), yet costs the generator
no fine-tuning, so one asyncio process drives 1024 agents on little CPU.

One server (default settings but the submission quotas, which would refuse a thousand
participants from one address), its own temporary data folder, SQLite (or ``--postgres``
with ``--replicas``), started here on 127.0.0.1. For every transport and every size in
``--agents`` the benchmark submits fresh agents, starts their auctions at once, plays them to
their end and reports:

- server CPU per upload: the CPU the server's processes used from the auctions' creation to
  their end (``/proc/<pid>/stat``: the API, its live children and the children it reaped),
  the screening process (named ``srd-screening``) excluded and reported apart, divided by
  the uploads answered;
- upload latency p50/p99 (upload sent → its answer) and the errors: non-200 answers,
  uploads never answered, asked patrons left ``missing`` or ``late``;
- round close latency p50/p95: a round's last answer (as this process received it) to the
  round's ``closed_at`` (``GET /auctions/{id}``). The verdict that judges a round's last
  upload closes the round in its own transaction, before its answer is sent: a negative figure
  is a round closed before its last answer reached the agent;
- next round latency p50/p95: a round's last answer to the first agent told that the next
  round is open (the close, the step that plays the next iteration and opens the round, and
  its push or long poll).

Budgets (printed as met or not): CPU per upload ≤ 1 ms over sockets, ≤ 2 ms over long poll +
PUT; upload p99 ≤ 250 ms at 1024 agents; no errors; close p95 ≤ 50 ms at 64 agents, ≤ 150 ms at
1024. The table goes to stdout, the JSON report and the plot to ``--out``.

Run: ``.venv/bin/python benchmarks/capacity.py [--agents 8,64,256,1024]
[--transports websocket,http] [--rounds 3] [--iterations 4] [--think 1,5]
[--postgres ADMIN_URL --replicas 2] [--out DIR]``
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import math
import os
import random
import secrets
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlencode, urlsplit

import h11
import httpx
import numpy as np
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from server.cli.launch import ServerProcess, settings_environment
from tests.support.databases import throwaway_postgres
from tests.support.processes import cpu_seconds, descendants, process_name, reaped_cpu_seconds
from tests.support.server import QUOTAS_OFF

ADMIN_TOKEN = secrets.token_hex(16)
AUCTION_SIZE = 64
"""Agents per auction: at 1024 agents, 16 auctions of 64 live at once."""
FISH_PER_PATRON = 0.1
"""Few fish (6 for 64 patrons, at least 1): demand stays high, so most agents are still asked
in every round."""
UPLOAD_STEP = 1e-3
"""Each round's upload moves the decision biases (B, L, Q) by this times the round: a new
version for the screener to judge, well inside what it accepts of honest fine-tuning."""
WAIT_S = 25.0
"""Long poll ``?wait=``."""
RECONNECTS = 3
"""Times a request is sent again on a fresh connection before it counts as failed."""
ANSWER_TIMEOUT_S = 60.0
"""An upload not answered in this long counts as unanswered (an error)."""
SCREENING_NAME = "srd-screening"
"""The screening process's name in ``/proc/<pid>/stat``: excluded from the server's CPU."""
WARM_UP_AGENTS = 8
"""One unmeasured auction this size per transport and replica first: it starts the auction
workers."""
JSON_TYPE = {"Content-Type": "application/json"}
SUBMIT_CONCURRENCY = 16
CONNECT_CONCURRENCY = 64
"""Socket handshakes in flight at once (a steady stream rather than a thousand at once)."""
CPU_BUDGET_MS = {"websocket": 1.0, "http": 2.0}
"""Server CPU per upload, screening process excluded, per transport."""
UPLOAD_P99_BUDGET_MS = {1024: 250.0}
CLOSE_P95_BUDGET_MS = {64: 50.0, 1024: 150.0}


@dataclass(frozen=True)
class Plan:
    """What every size plays."""

    rounds: int
    iterations: int
    deadline_s: float
    think_s: tuple[float, float]
    seed: int


def prebuilt_uploads(manifest: Manifest, rounds: int) -> list[bytes]:
    """The agent's upload for rounds 1..``rounds``, built once before the run."""
    uploads = []
    for number in range(1, rounds + 1):
        data = manifest.model_dump(mode="json")
        for neuron in data["decision"].values():
            neuron["bias"] += UPLOAD_STEP * number
        uploads.append(Manifest.model_validate(data).model_dump_json().encode())
    return uploads


class ServerCpu:
    """CPU seconds of the server's processes (one root per replica), read from ``/proc``."""

    def __init__(self, roots: Sequence[int]) -> None:
        self.roots = list(roots)

    def _tree(self) -> Iterator[tuple[int, str]]:
        for root in self.roots:
            for pid in descendants(root)[1:]:
                yield pid, process_name(pid) or ""

    def read(self) -> dict[str, float]:
        """CPU seconds so far by part: the replicas' own (``api event loop``: their main
        thread; ``api other threads``: the thread pool's database work and the rest),
        ``reaped`` (children that ended and were waited for: workers, by the fork server that
        started them), then each live process below by name (the screening process, the
        auction workers, the fork server, multiprocessing's resource tracker)."""
        api = sum(cpu_seconds(r) or 0.0 for r in self.roots)
        loop = sum(cpu_seconds(f"{r}/task/{r}") or 0.0 for r in self.roots)
        parts = {
            "api event loop": loop,
            "api other threads": api - loop,
            "reaped": sum(reaped_cpu_seconds(r) or 0.0 for r in self.roots)
            + sum(reaped_cpu_seconds(pid) or 0.0 for pid, _ in self._tree()),
        }
        for pid, name in self._tree():
            parts[name] = parts.get(name, 0.0) + (cpu_seconds(pid) or 0.0)
        return parts

    def check(self, wait_s: float = 60.0) -> None:
        """Each replica has its screening process, found by name (else the figures lie); a
        replica just started may still be starting it."""
        deadline = time.monotonic() + wait_s
        while (found := sum(name == SCREENING_NAME for _, name in self._tree())) != len(self.roots):
            if time.monotonic() > deadline:
                raise SystemExit(
                    f"found {found} '{SCREENING_NAME}' processes for {len(self.roots)}"
                )
            time.sleep(0.1)


@dataclass
class Upload:
    auction_id: int
    round: int
    model_id: int
    latency_s: float | None
    """None: never answered."""
    status: int | None
    accepted: bool
    answered_at: float
    """Wall-clock time the answer arrived."""
    told_at: float
    """Wall-clock time the agent learned that the round was open (a push, a long poll)."""


@dataclass
class AgentSpec:
    model_id: int
    token: str
    auction_id: int
    server: str
    uploads: list[bytes]
    rng: random.Random
    address: str
    """The loopback address the agent connects from (each agent a machine of its own, as the
    server's per-client limits expect)."""


def agent_address(index: int) -> str:
    """Agent ``index``'s own loopback address: 127.0.1.1, 127.0.1.2, ... (Linux routes all of
    127/8 to loopback)."""
    return f"127.0.{1 + index // 250}.{1 + index % 250}"


@dataclass
class SizeResult:
    transport: str
    agents: int
    auctions: int
    replicas: int
    asked: int
    """Patron-rounds the auctions asked for (each asked patron of each round)."""
    uploads: int
    """Uploads answered."""
    accepted: int
    refused: int
    errors: int
    error_kinds: dict[str, int]
    upload_p50_ms: float
    upload_p99_ms: float
    close_p50_ms: float
    close_p95_ms: float
    close_max_ms: float
    """The slowest round's close (a round that waited for its deadline shows here)."""
    rounds_closed: int
    next_round_p50_ms: float
    next_round_p95_ms: float
    """A round's last answer to the first agent told that the next round is open (the close,
    the step that plays the next iteration and opens the round, and the push or long poll)."""
    server_cpu_ms_per_upload: float
    screening_cpu_ms_per_upload: float
    cpu_ms_per_upload_by_process: dict[str, float]
    """The server's CPU per upload by part (see ``ServerCpu.read``), the screening included."""
    generator_cpu_ms_per_upload: float
    wall_s: float
    load_average: list[float]
    """1, 5 and 15 minute load averages at the start, then at the end."""
    reconnects: dict[str, int]
    """Requests sent again on a fresh connection (by method): not errors, but counted."""
    budgets: dict[str, bool] = field(default_factory=dict)


def checked(response: httpx.Response) -> httpx.Response:
    """The response, or stop the run with what the server said."""
    if response.is_error:
        raise SystemExit(f"{response.request.method} {response.url}: {response.text}")
    return response


def stamp(text: str) -> float:
    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else math.nan


async def think(agent: AgentSpec, plan: Plan) -> None:
    await asyncio.sleep(agent.rng.uniform(*plan.think_s))


async def socket_agent(
    agent: AgentSpec, plan: Plan, handshakes: asyncio.Semaphore, log: list[Upload]
) -> None:
    """One agent over its round socket: each round it is asked in, think, upload, note the
    answer; it leaves when not asked (bought or quit) or when the server ends the auction."""
    url = agent.server.replace("http://", "ws://") + f"/auctions/{agent.auction_id}/rounds/socket"
    sent: dict[int, float] = {}
    told: dict[int, float] = {}
    pending: set[int] = set()
    handled = 0

    async def answer_round(ws: ClientConnection, number: int) -> None:
        await think(agent, plan)
        frame = {
            "type": "upload",
            "round": number,
            "model_id": agent.model_id,
            "manifest": agent.uploads[number - 1].decode(),
        }
        sent[number] = time.time()
        pending.add(number)
        await ws.send(json.dumps(frame))

    async with handshakes:  # a steady stream of handshakes, not a thousand at once
        ws = await connect(
            url,
            additional_headers={"Authorization": f"Bearer {agent.token}"},
            max_size=1 << 20,
            compression=None,  # as the project's agent connects (agents/remote/socket.py)
            local_addr=(agent.address, 0),
        )
    thinking: list[asyncio.Task[None]] = []
    async with ws:
        with contextlib.suppress(ConnectionClosed, TimeoutError):
            while True:
                # Bounded only while an upload is on its way or awaits its answer: a round
                # may rightly wait for its deadline before the next one is pushed.
                busy = pending or any(not task.done() for task in thinking)
                frame = await asyncio.wait_for(ws.recv(), ANSWER_TIMEOUT_S if busy else None)
                now = time.time()
                message = json.loads(frame)
                if message["type"] == "answer":
                    number = message["round"]
                    pending.discard(number)
                    accepted = message["status"] == 200 and bool(message["body"]["accepted"])
                    log.append(
                        Upload(
                            agent.auction_id,
                            number,
                            agent.model_id,
                            now - sent[number],
                            message["status"],
                            accepted,
                            now,
                            told[number],
                        )
                    )
                    continue
                thinking = [t for t in thinking if not t.done()]
                state = message["body"]
                if state["auction_status"] not in ("pending", "running"):
                    break
                if state["status"] != "open" or state["round"] <= handled:
                    continue
                if agent.model_id not in state["asked"]:
                    break
                handled = state["round"]
                told[handled] = now
                thinking.append(asyncio.create_task(answer_round(ws, handled)))
        for task in thinking:
            task.cancel()
    log.extend(
        Upload(agent.auction_id, r, agent.model_id, None, None, False, 0.0, told[r])
        for r in pending
    )


class AgentConnection:
    """One agent's kept-alive HTTP/1.1 connection from its own loopback address, spoken with
    h11 over asyncio streams: a few tens of microseconds per request where a general client
    (httpx) spends about a millisecond, so the generator's CPU stays small beside the server's.
    A request whose connection the server closed under it (idle for 5 s while the agent
    thinks) is sent again, with the same bytes, on a fresh one: counted in ``reconnects``, as a
    real agent's client would retry it; a timeout is not retried."""

    def __init__(self, server: str, address: str, reconnects: Counter[str]) -> None:
        parts = urlsplit(server)
        self.host, self.port = parts.hostname or "127.0.0.1", parts.port or 80
        self.address = address
        self.reconnects = reconnects
        self._streams: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        self._h11 = h11.Connection(h11.CLIENT)

    async def request(
        self,
        method: str,
        path: str,
        *,
        body: bytes = b"",
        headers: Sequence[tuple[str, str]] = (),
        timeout: float,
    ) -> tuple[int, bytes]:
        """(status, body) of the request, within ``timeout`` s (else ``TimeoutError``)."""
        for attempt in range(RECONNECTS + 1):
            try:
                return await asyncio.wait_for(self._exchange(method, path, body, headers), timeout)
            except TimeoutError:  # an OSError since Python 3.11, but not retried
                self.close()
                raise
            except (OSError, EOFError, h11.ProtocolError):
                self.close()
                if attempt == RECONNECTS:
                    raise
                self.reconnects[method] += 1
            except BaseException:
                self.close()
                raise
        raise AssertionError("unreachable")

    async def _exchange(
        self, method: str, path: str, body: bytes, headers: Sequence[tuple[str, str]]
    ) -> tuple[int, bytes]:
        if self._streams is None:
            self._streams = await asyncio.open_connection(
                self.host, self.port, local_addr=(self.address, 0)
            )
            self._h11 = h11.Connection(h11.CLIENT)
        reader, writer = self._streams
        fields = [("Host", f"{self.host}:{self.port}"), ("Content-Length", str(len(body)))]
        connection = self._h11
        writer.write(
            connection.send(h11.Request(method=method, target=path, headers=[*fields, *headers]))
            + (connection.send(h11.Data(data=body)) or b"" if body else b"")
            + (connection.send(h11.EndOfMessage()) or b"")
        )
        await writer.drain()
        status, chunks = 0, []
        while True:
            event = connection.next_event()
            if event is h11.NEED_DATA:
                data = await reader.read(1 << 16)
                if not data:
                    raise EOFError("the server closed the connection")
                connection.receive_data(data)
            elif isinstance(event, h11.Response):
                status = event.status_code
            elif isinstance(event, h11.Data):
                chunks.append(bytes(event.data))
            elif isinstance(event, h11.EndOfMessage):
                break
            elif isinstance(event, h11.ConnectionClosed):
                raise EOFError("the server closed the connection")
        if connection.our_state is h11.DONE and connection.their_state is h11.DONE:
            connection.start_next_cycle()
        else:  # the server asked to close (Connection: close)
            self.close()
        return status, b"".join(chunks)

    def close(self) -> None:
        if self._streams is not None:
            self._streams[1].close()
            self._streams = None


async def http_agent(
    agent: AgentSpec, plan: Plan, connection: AgentConnection, log: list[Upload]
) -> None:
    """One agent by long poll + PUT, otherwise as ``socket_agent``."""
    after = 0
    base = f"/auctions/{agent.auction_id}/rounds"
    put_headers = [("Authorization", f"Bearer {agent.token}"), *JSON_TYPE.items()]
    try:
        while True:
            query = urlencode({"wait": WAIT_S, "after": after})
            status, body = await connection.request(  # with the token: a patron's share
                "GET", f"{base}/current?{query}", headers=put_headers[:1], timeout=WAIT_S + 15
            )
            if status != 200:
                raise RuntimeError(f"GET {base}/current answered {status}: {body[:300]!r}")
            state = json.loads(body)
            if state["auction_status"] not in ("pending", "running"):
                return
            if state["status"] != "open" or state["round"] <= after:
                continue
            if agent.model_id not in state["asked"]:
                return
            after = state["round"]
            told = time.time()
            await think(agent, plan)
            sent = time.time()
            try:
                status, body = await connection.request(
                    "PUT",
                    f"{base}/{after}/models/{agent.model_id}",
                    body=agent.uploads[after - 1],
                    headers=put_headers,
                    timeout=ANSWER_TIMEOUT_S,
                )
            except TimeoutError:
                log.append(
                    Upload(agent.auction_id, after, agent.model_id, None, None, False, 0.0, told)
                )
                continue
            now = time.time()
            accepted = status == 200 and bool(json.loads(body).get("accepted"))
            log.append(
                Upload(
                    agent.auction_id, after, agent.model_id, now - sent, status, accepted, now, told
                )
            )
    finally:
        connection.close()


async def submit_agents(
    client: httpx.AsyncClient, server: str, count: int, seed: int, plan: Plan
) -> list[tuple[int, str, list[bytes]]]:
    """``count`` honest participants submitted (redrawing the few the screener refuses), with
    their pre-built uploads: (model id, token, uploads)."""
    rng = np.random.default_rng(seed)
    tag = secrets.token_hex(3)
    limit = asyncio.Semaphore(SUBMIT_CONCURRENCY)
    agents: list[tuple[int, str, list[bytes]]] = []
    drawn = 0

    async def submit(manifest: Manifest) -> tuple[int, str, list[bytes]] | None:
        async with limit:
            response = await client.post(
                f"{server}/submit", content=manifest.model_dump_json(), headers=JSON_TYPE
            )
        answer = checked(response).json()
        if not answer["accepted"]:
            return None
        return answer["model_id"], answer["token"], prebuilt_uploads(manifest, plan.rounds)

    while len(agents) < count:
        lacking = count - len(agents)
        manifests = [honest_manifest(rng, f"cap-{tag}-{drawn + i:04d}") for i in range(lacking)]
        drawn += lacking
        agents += [a for a in await asyncio.gather(*map(submit, manifests)) if a is not None]
    return agents


async def play_size(
    servers: list[str], cpu: ServerCpu, transport: str, n_agents: int, plan: Plan
) -> SizeResult:
    """Submit ``n_agents`` agents, start their auctions, play them to their end, measure."""
    admin = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    async with contextlib.AsyncExitStack() as stack:
        client = await stack.enter_async_context(httpx.AsyncClient(timeout=WAIT_S + 15))
        joined = await submit_agents(client, servers[0], n_agents, plan.seed + n_agents, plan)
        groups = [joined[i : i + AUCTION_SIZE] for i in range(0, n_agents, AUCTION_SIZE)]
        print(f"{transport} {n_agents}: agents submitted, measuring from here", file=sys.stderr)
        load = list(os.getloadavg())
        cpu_before = cpu.read()
        generator_before, wall_before = time.process_time(), time.monotonic()
        auction_ids = []
        for k, group in enumerate(groups):
            body = {
                "n_fish": max(1, int(FISH_PER_PATRON * len(group))),
                "model_ids": [model_id for model_id, _, _ in group],
                "fine_tune_mode": "remote",
                "fine_tune_rounds": plan.rounds,
                "max_iterations": plan.iterations,
                "round_deadline_s": plan.deadline_s,
                "seed": plan.seed + k,
            }
            created = await client.post(f"{servers[0]}/auctions", json=body, headers=admin)
            checked(created)
            auction_ids.append(created.json()["auction_id"])
        specs = [
            AgentSpec(
                model_id,
                token,
                auction_id,
                servers[i % len(servers)],
                uploads,
                random.Random(plan.seed * 1_000_003 + model_id),
                agent_address(k * AUCTION_SIZE + i),
            )
            for k, (auction_id, group) in enumerate(zip(auction_ids, groups, strict=True))
            for i, (model_id, token, uploads) in enumerate(group)
        ]
        log: list[Upload] = []
        reconnects: Counter[str] = Counter()
        if transport == "websocket":
            handshakes = asyncio.Semaphore(CONNECT_CONCURRENCY)
            await asyncio.gather(*(socket_agent(s, plan, handshakes, log) for s in specs))
        else:  # one connection per agent, as on its own machine
            await asyncio.gather(
                *(
                    http_agent(s, plan, AgentConnection(s.server, s.address, reconnects), log)
                    for s in specs
                )
            )
        auctions = [await wait_finished(client, servers[0], a) for a in auction_ids]
        cpu_after = cpu.read()
        generator = time.process_time() - generator_before
        wall = time.monotonic() - wall_before
    return summarise(
        transport,
        n_agents,
        len(servers),
        log,
        auctions,
        {k: v - cpu_before.get(k, 0.0) for k, v in cpu_after.items()},
        generator,
        wall,
        load + list(os.getloadavg()),
        dict(reconnects),
    )


async def wait_finished(client: httpx.AsyncClient, server: str, auction_id: int) -> Any:
    """The auction's state once it has ended (its last steps play after the last round)."""
    while True:
        state = (await client.get(f"{server}/auctions/{auction_id}")).json()
        if state["status"] not in ("pending", "running"):
            return state
        await asyncio.sleep(0.2)


def summarise(
    transport: str,
    n_agents: int,
    replicas: int,
    log: list[Upload],
    auctions: list[Any],
    server_cpu: dict[str, float],
    generator_cpu: float,
    wall: float,
    load: list[float],
    reconnects: dict[str, int],
) -> SizeResult:
    answered = [u for u in log if u.status is not None]
    errors: dict[str, int] = {}
    for u in log:
        if u.status is None:
            errors["unanswered"] = errors.get("unanswered", 0) + 1
        elif u.status != 200:
            errors[f"status {u.status}"] = errors.get(f"status {u.status}", 0) + 1
    last_answer: dict[tuple[int, int], float] = {}
    for u in answered:
        key = (u.auction_id, u.round)
        last_answer[key] = max(last_answer.get(key, 0.0), u.answered_at)
    told: dict[tuple[int, int], float] = {}
    for u in log:
        key = (u.auction_id, u.round)
        told[key] = min(told.get(key, math.inf), u.told_at)
    follows = [
        told[auction_id, number + 1] - answered_last
        for (auction_id, number), answered_last in last_answer.items()
        if (auction_id, number + 1) in told
    ]
    closes = []
    for auction in auctions:
        if auction["status"] != "finished":
            errors[f"auction {auction['status']}"] = (
                errors.get(f"auction {auction['status']}", 0) + 1
            )
        for played in auction["fine_tuning"]:
            for answer in played["answers"]:
                if answer["outcome"] in ("missing", "late"):
                    errors[answer["outcome"]] = errors.get(answer["outcome"], 0) + 1
            key = (auction["id"], played["round"])
            if played["closed_at"] is not None and key in last_answer:
                closes.append(stamp(played["closed_at"]) - last_answer[key])
    uploads = max(len(answered), 1)
    latencies = [u.latency_s for u in answered if u.latency_s is not None]
    accepted = sum(u.accepted for u in answered)
    result = SizeResult(
        transport=transport,
        agents=n_agents,
        auctions=len(auctions),
        replicas=replicas,
        asked=sum(len(played["answers"]) for a in auctions for played in a["fine_tuning"]),
        uploads=len(answered),
        accepted=accepted,
        refused=sum(u.status == 200 and not u.accepted for u in answered),
        errors=sum(errors.values()),
        error_kinds=errors,
        upload_p50_ms=percentile(latencies, 50) * 1e3,
        upload_p99_ms=percentile(latencies, 99) * 1e3,
        close_p50_ms=percentile(closes, 50) * 1e3,
        close_p95_ms=percentile(closes, 95) * 1e3,
        close_max_ms=max(closes, default=math.nan) * 1e3,
        rounds_closed=len(closes),
        next_round_p50_ms=percentile(follows, 50) * 1e3,
        next_round_p95_ms=percentile(follows, 95) * 1e3,
        server_cpu_ms_per_upload=sum(v for k, v in server_cpu.items() if k != SCREENING_NAME)
        / uploads
        * 1e3,
        screening_cpu_ms_per_upload=server_cpu.get(SCREENING_NAME, 0.0) / uploads * 1e3,
        cpu_ms_per_upload_by_process={k: v / uploads * 1e3 for k, v in server_cpu.items()},
        generator_cpu_ms_per_upload=generator_cpu / uploads * 1e3,
        wall_s=wall,
        load_average=[round(v, 2) for v in load],
        reconnects=reconnects,
    )
    result.budgets = budgets_of(result)
    return result


def budgets_of(result: SizeResult) -> dict[str, bool]:
    """The budgets that apply at this size, each met or not."""
    met = {
        "cpu_per_upload": result.server_cpu_ms_per_upload <= CPU_BUDGET_MS[result.transport],
        "no_errors": result.errors == 0,
    }
    if result.agents in UPLOAD_P99_BUDGET_MS:
        met["upload_p99"] = result.upload_p99_ms <= UPLOAD_P99_BUDGET_MS[result.agents]
    if result.agents in CLOSE_P95_BUDGET_MS:
        met["close_p95"] = result.close_p95_ms <= CLOSE_P95_BUDGET_MS[result.agents]
    return met


def print_table(results: list[SizeResult]) -> None:
    columns = (
        f"{'transport':<9} {'agents':>6} {'uploads':>7} {'errors':>6} {'CPU ms/up':>9} "
        f"{'screen ms/up':>12} {'gen ms/up':>9} {'up p50':>7} {'up p99':>7} {'close p50':>9} "
        f"{'close p95':>9} {'next p50':>8} {'next p95':>8} {'wall s':>6}  budgets"
    )
    print(columns)
    for r in results:
        budgets = " ".join(f"{k}={'met' if v else 'NOT met'}" for k, v in r.budgets.items())
        print(
            f"{r.transport:<9} {r.agents:>6} {r.uploads:>7} {r.errors:>6} "
            f"{r.server_cpu_ms_per_upload:9.3f} {r.screening_cpu_ms_per_upload:12.3f} "
            f"{r.generator_cpu_ms_per_upload:9.3f} {r.upload_p50_ms:7.1f} {r.upload_p99_ms:7.1f} "
            f"{r.close_p50_ms:9.1f} {r.close_p95_ms:9.1f} {r.next_round_p50_ms:8.1f} "
            f"{r.next_round_p95_ms:8.1f} {r.wall_s:6.1f}  {budgets}"
        )


def plot(results: Sequence[dict[str, Any]], path: Path) -> None:
    """Server CPU per upload and the latencies against the agents (the JSON report's
    ``results``): round sockets solid, long poll + PUT dashed, budgets as grey marks."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (cpu_axis, latency_axis) = plt.subplots(1, 2, figsize=(11, 4.2))
    for transport, line, marker in (("websocket", "-", "o"), ("http", "--", "s")):
        mine = [r for r in results if r["transport"] == transport]
        if not mine:
            continue
        agents = [r["agents"] for r in mine]
        for value, name, colour in (
            ("server_cpu_ms_per_upload", "server", "C0"),
            ("screening_cpu_ms_per_upload", "screening process", "C2"),
        ):
            cpu_axis.plot(
                agents,
                [r[value] for r in mine],
                line + marker,
                color=colour,
                label=f"{name}, {transport}",
            )
        cpu_axis.axhline(CPU_BUDGET_MS[transport], color="grey", linestyle=line, lw=0.8)
        for value, name, colour in (
            ("upload_p50_ms", "upload p50", "C0"),
            ("upload_p99_ms", "upload p99", "C3"),
            ("next_round_p95_ms", "next round p95", "C1"),
        ):
            latency_axis.plot(
                agents,
                [r[value] for r in mine],
                line + marker,
                color=colour,
                label=f"{name}, {transport}",
            )
    for budgets, colour in ((UPLOAD_P99_BUDGET_MS, "C3"), (CLOSE_P95_BUDGET_MS, "C1")):
        latency_axis.plot(list(budgets), list(budgets.values()), "x", color=colour, ms=10)
    for axis in (cpu_axis, latency_axis):
        axis.set_xscale("log", base=2)
        axis.set_xlabel("connected agents (auctions of 64)")
        axis.legend(fontsize=7)
    cpu_axis.set_ylabel("CPU ms per upload")
    cpu_axis.set_title("CPU per upload (grey lines: server budgets)")
    latency_axis.set_ylabel("ms")
    latency_axis.set_yscale("log")
    latency_axis.set_title("latencies (x: upload p99 and round close budgets)")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def sizes(text: str) -> list[int]:
    values = [int(v) for v in text.split(",")]
    if any(v < 1 for v in values):
        raise argparse.ArgumentTypeError("sizes are positive agent counts")
    return values


def think_range(text: str) -> tuple[float, float]:
    low, high = (float(v) for v in text.split(","))
    if not 0 <= low <= high:
        raise argparse.ArgumentTypeError("--think is LOW,HIGH seconds with 0 ≤ LOW ≤ HIGH")
    return low, high


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--agents", type=sizes, default=[8, 64, 256, 1024], help="sizes")
    parser.add_argument(
        "--transports",
        type=lambda t: t.split(","),
        default=["websocket", "http"],
        help="websocket (round sockets), http (long poll + PUT), or both",
    )
    parser.add_argument("--rounds", type=int, default=3, help="fine-tuning rounds per auction")
    parser.add_argument("--iterations", type=int, default=4, help="max_iterations per auction")
    parser.add_argument("--deadline", type=float, default=120.0, help="round_deadline_s")
    parser.add_argument("--think", type=think_range, default=(1.0, 5.0), help="LOW,HIGH s")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--postgres", metavar="ADMIN_URL", help="a throw-away database there")
    parser.add_argument("--replicas", type=int, default=1, help="API replicas (PostgreSQL)")
    parser.add_argument("--out", type=Path, help="folder for capacity.json and capacity.png")
    args = parser.parse_args(argv)
    if set(args.transports) - {"websocket", "http"}:
        parser.error("--transports: websocket, http")
    if args.replicas > 1 and not args.postgres:
        parser.error("--replicas above 1 needs --postgres (replicas share one database)")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse_args(argv)
    plan = Plan(args.rounds, args.iterations, args.deadline, args.think, args.seed)
    stamp_now = time.strftime("%Y%m%d-%H%M%S")
    out: Path = args.out or Path("runs") / f"capacity__{args.seed}__{stamp_now}"
    out.mkdir(parents=True, exist_ok=True)
    with ExitStack() as stack:
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        url = f"sqlite:///{folder / 'srd.db'}"
        if args.postgres:
            url = stack.enter_context(throwaway_postgres(args.postgres))
        environment = settings_environment({**QUOTAS_OFF})
        servers = [
            stack.enter_context(
                ServerProcess(
                    database_url=url,
                    data_dir=folder / "data",
                    admin_token=ADMIN_TOKEN,
                    extra_env=environment,
                    log_path=folder / f"serve-{k}.log",
                )
            )
            for k in range(args.replicas)
        ]
        roots = [s.process.pid for s in servers if s.process is not None]
        cpu = ServerCpu(roots)
        time.sleep(2.0)  # the screening processes start in the background
        cpu.check()
        print(
            f"srd serve ×{args.replicas} ({'PostgreSQL' if args.postgres else 'SQLite'}), "
            f"{args.rounds} rounds, think {args.think[0]}-{args.think[1]} s, "
            f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; "
            f"server pids {' '.join(map(str, roots))} (to profile)",
            file=sys.stderr,
        )
        urls = [s.url for s in servers]
        # Unmeasured: starts the auction worker processes (torch's import) and warms the API,
        # an auction on each replica (created there, its agents there: its steps run there).
        warm_up = dataclasses.replace(plan, think_s=(0.0, 0.1))
        for transport in args.transports:
            for url in urls:
                asyncio.run(play_size([url], cpu, transport, WARM_UP_AGENTS, warm_up))
        results = []
        for transport in args.transports:
            for n_agents in args.agents:
                result = asyncio.run(play_size(urls, cpu, transport, n_agents, plan))
                print(
                    f"{transport} {n_agents}: {result.uploads} uploads, "
                    f"{result.server_cpu_ms_per_upload:.3f} ms CPU each, {result.wall_s:.1f} s",
                    file=sys.stderr,
                )
                results.append(result)
    print_table(results)
    report = {
        "plan": asdict(plan),
        "backend": "postgresql" if args.postgres else "sqlite",
        "replicas": args.replicas,
        "cores": os.cpu_count(),
        "results": [asdict(r) for r in results],
    }
    (out / "capacity.json").write_text(json.dumps(report, indent=2) + "\n")
    plot(report["results"], out / "capacity.png")
    print(f"report: {out / 'capacity.json'}, plot: {out / 'capacity.png'}")


if __name__ == "__main__":
    main()
