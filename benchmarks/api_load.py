"""Loopback load on the HTTP API while auctions run: POST /submit and GET /auctions/{id}.

For each database (SQLite file, and the local PostgreSQL when reachable) it starts ``srd serve``
in a fresh data folder, registers 32 honest patrons and keeps an auction of those 32 running
the whole time (one more is always queued behind the running one; ``--fine-tune`` makes them
fine-tune). Then, from httpx clients in this process:

1. **closed loop** (``--concurrency`` clients, each sending its next request when the last is
   answered, ``--requests`` at most, ``--seconds`` at most): the most the server answers.
   Phases: POST /submit, GET /auctions/{id}, GET /healthz (the HTTP stack alone).
2. **open loop** (the target): POST /submit offered at a fixed rate (``--rate``/s for
   ``--open-seconds``), each request sent at its scheduled time whether or not earlier ones
   were answered, latency counted from the scheduled time (no coordinated omission).

Each submit registers a new participant (screening, token hashing, two inserts; commits are
grouped). Prints requests/s, p50 and p99 latency, errors, the share of the phase with an
auction running, and the API process's CPU time per request (Linux). Target: POST /submit at
≥ 300/s with p99 < 100 ms and no errors, while an auction runs (the open-loop phase). Load
generator, API, screening process, auction worker (and the database server) share the
machine's cores, so the numbers are a floor, and noisy when anything else runs.

Run: ``.venv/bin/python benchmarks/api_load.py [--backend sqlite|postgresql|both]``
"""

from __future__ import annotations

import argparse
import asyncio
import json
import secrets
import statistics
import sys
import tempfile
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import httpx
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # for tests.support

from agents.negotiator import honest_manifest
from server.cli.launch import ServerProcess, settings_environment
from tests.support.databases import postgres_admin_url, throwaway_postgres
from tests.support.processes import cpu_seconds
from tests.support.server import QUOTAS_OFF

torch.set_num_threads(1)

PATRONS = 32
WARMUP_REQUESTS = 50
TARGET_RPS = 300
TARGET_P99_MS = 100
KEEPER_POLL_S = 0.05
# Open loop: with this many requests unanswered, a send that falls due is counted as an error
# instead of being queued (the server is hopelessly behind; waiting requests cost memory).
MAX_IN_FLIGHT = 2048


@dataclass
class PhaseResult:
    name: str
    mode: str
    """"closed" (fixed concurrency) or "open" (fixed arrival rate)."""
    requests: int
    errors: int
    seconds: float
    p50_ms: float
    p99_ms: float
    auction_running: float
    """Share of the phase during which an auction was running (server timestamps)."""
    server_cpu_ms: float | None
    """CPU time of the API process per request (None where /proc is missing)."""
    load_cpu_ms: float
    """CPU time of this process (the load generator) per request."""

    @property
    def rps(self) -> float:
        return self.requests / self.seconds

    def meets_target(self) -> bool:
        return self.rps >= TARGET_RPS and self.p99_ms < TARGET_P99_MS and self.errors == 0


class AuctionKeeper:
    """Keeps an auction of the registered patrons running all the time: one more is always
    queued behind the running one, and a new one is queued whenever one ends."""

    def __init__(
        self,
        client: httpx.AsyncClient,
        admin: dict[str, str],
        fine_tune: bool,
        patrons: list[int],
    ) -> None:
        self.client = client
        self.admin = admin
        self.fine_tune = fine_tune
        self.patrons = patrons
        """Every auction has these (not every accepted model so far, which would grow with the
        load's own submissions)."""
        self.unfinished: deque[int] = deque()
        self.queued: list[int] = []
        self.started = 0
        self._stop = asyncio.Event()

    @property
    def auction_id(self) -> int | None:
        """The oldest unfinished auction (the one running, or about to)."""
        return self.unfinished[0] if self.unfinished else None

    async def _queue_one(self) -> None:
        response = await self.client.post(
            "/auctions",
            json={
                "rarity": 0.25,
                "fine_tune": self.fine_tune,
                "seed": self.started,
                "model_ids": self.patrons,
            },
            headers=self.admin,
        )
        response.raise_for_status()
        self.unfinished.append(int(response.json()["auction_id"]))
        self.queued.append(self.unfinished[-1])
        self.started += 1

    async def run(self) -> None:
        while not self._stop.is_set():
            while len(self.unfinished) < 2:
                await self._queue_one()
            status = (await self.client.get(f"/auctions/{self.unfinished[0]}")).json()["status"]
            if status in ("finished", "failed"):
                self.unfinished.popleft()
            else:
                await asyncio.sleep(KEEPER_POLL_S)

    def stop(self) -> None:
        self._stop.set()

    async def running_share(self, start: datetime, end: datetime) -> float:
        """The share of [start, end] during which one of our auctions was running, from the
        server's own started_at/finished_at (the union of those intervals)."""
        spans = []
        for auction_id in self.queued:
            auction = (await self.client.get(f"/auctions/{auction_id}")).json()
            if auction["started_at"] is None:
                continue
            began = datetime.fromisoformat(auction["started_at"])
            ended = (
                datetime.fromisoformat(auction["finished_at"]) if auction["finished_at"] else end
            )
            spans.append((max(began, start), min(ended, end)))
        covered = timedelta()
        reach = start
        for began, ended in sorted(spans):
            if ended > reach:
                covered += ended - max(began, reach)
                reach = ended
        return covered / (end - start)


Request = Callable[[int], Awaitable[httpx.Response]]


async def _timed(request: Request, i: int, since: float) -> tuple[float, bool]:
    """Latency from ``since`` (perf_counter) and whether the answer was a success."""
    try:
        response = await request(i)
        ok = response.status_code < 400
    except httpx.HTTPError:
        ok = False
    return time.perf_counter() - since, ok


async def closed_loop(
    request: Request, *, total: int, seconds: float, concurrency: int
) -> tuple[list[float], int]:
    """``total`` requests (or until ``seconds``) from ``concurrency`` clients, each sending its
    next request when its last one is answered. Latencies (s) and error count."""
    latencies: list[float] = []
    errors = 0
    counter = iter(range(total))
    deadline = time.perf_counter() + seconds

    async def client() -> None:
        nonlocal errors
        for i in counter:
            if time.perf_counter() > deadline:
                return
            latency, ok = await _timed(request, i, time.perf_counter())
            latencies.append(latency)
            errors += not ok

    await asyncio.gather(*(client() for _ in range(concurrency)))
    return latencies, errors


async def open_loop(request: Request, *, total: int, rate: float) -> tuple[list[float], int]:
    """``total`` requests offered at ``rate`` per second: request i is sent at start + i/rate
    whatever happened to the earlier ones, and its latency runs from that scheduled time, so
    a slow server cannot slow the load down and hide its own queueing."""
    latencies: list[float] = []
    errors = 0
    tasks: set[asyncio.Task[tuple[float, bool]]] = set()

    def done(task: asyncio.Task[tuple[float, bool]]) -> None:
        nonlocal errors
        tasks.discard(task)
        latency, ok = task.result()
        latencies.append(latency)
        errors += not ok

    start = time.perf_counter()
    for i in range(total):
        scheduled = start + i / rate
        delay = scheduled - time.perf_counter()
        if delay > 0:
            await asyncio.sleep(delay)
        if len(tasks) >= MAX_IN_FLIGHT:  # the server is hopelessly behind: count, don't send
            errors += 1
            continue
        task = asyncio.create_task(_timed(request, i, scheduled))
        tasks.add(task)
        task.add_done_callback(done)
    while tasks:
        await asyncio.sleep(0.01)
    return latencies, errors


async def phase(
    name: str,
    mode: str,
    run: Callable[[], Awaitable[tuple[list[float], int]]],
    *,
    keeper: AuctionKeeper,
    server_pid: int,
) -> PhaseResult:
    """Run one load phase and summarise it."""
    wall_start = datetime.now(UTC)
    began, cpu_before, load_before = (
        time.perf_counter(),
        cpu_seconds(server_pid),
        time.process_time(),
    )
    latencies, errors = await run()
    elapsed, cpu_after = time.perf_counter() - began, cpu_seconds(server_pid)
    load_cpu = time.process_time() - load_before
    running = await keeper.running_share(wall_start, datetime.now(UTC))
    ms = sorted(x * 1000 for x in latencies)
    return PhaseResult(
        name=name,
        mode=mode,
        requests=len(ms),
        errors=errors,
        seconds=elapsed,
        p50_ms=statistics.median(ms),
        p99_ms=ms[min(len(ms) - 1, int(0.99 * len(ms)))],
        auction_running=running,
        load_cpu_ms=load_cpu * 1000 / len(ms),
        server_cpu_ms=None
        if cpu_before is None or cpu_after is None
        else (cpu_after - cpu_before) * 1000 / len(ms),
    )


def manifest_bodies(count: int, tag: str) -> Iterator[bytes]:
    """Submit bodies: 16 weight sets in turn, each under a new participant name."""
    templates = [honest_manifest(np.random.default_rng(s), "PLACEHOLDER") for s in range(16)]
    texts = [json.dumps(t.model_dump(mode="json")) for t in templates]
    for i in range(count):
        yield texts[i % len(texts)].replace("PLACEHOLDER", f"{tag}-{i}").encode()


class LoadClient:
    """The load's own requests, over ``connections`` keep-alive connections.

    Each connection is its own one-connection httpx transport (a "lane"); a request takes a
    free lane, or waits for one. The load generator shares the machine's two cores with the
    server, so it must burn little CPU per request: it skips the client layer (cookies,
    redirects, auth, URL merging), and one pool of many connections would cost it time
    quadratic in the number of connections and waiting requests (httpcore re-examines every
    connection for every queued request). The keeper and the set-up use an ordinary
    ``httpx.AsyncClient``."""

    def __init__(self, base_url: str, connections: int) -> None:
        self.base_url = base_url
        self.lanes = [
            httpx.AsyncHTTPTransport(
                limits=httpx.Limits(max_connections=1, max_keepalive_connections=1)
            )
            for _ in range(connections)
        ]
        self._free: asyncio.Queue[httpx.AsyncHTTPTransport] = asyncio.Queue()
        for lane in self.lanes:
            self._free.put_nowait(lane)

    async def send(
        self,
        method: str,
        path: str,
        body: bytes | None = None,
        headers: dict[str, str] | None = None,
    ) -> httpx.Response:
        request = httpx.Request(method, self.base_url + path, content=body, headers=headers)
        lane = await self._free.get()
        try:
            response = await lane.handle_async_request(request)
            try:
                await response.aread()
            finally:
                await response.aclose()
        finally:
            self._free.put_nowait(lane)
        return response

    async def aclose(self) -> None:
        for lane in self.lanes:
            await lane.aclose()


async def measure(server: ServerProcess, args: argparse.Namespace) -> list[PhaseResult]:
    admin = {"Authorization": f"Bearer {server.admin_token}"}
    connections = max(args.concurrency, 64)
    load = LoadClient(server.url, connections)
    async with httpx.AsyncClient(base_url=server.url, timeout=30) as client:
        headers = {"Content-Type": "application/json"}
        patrons = []
        for body in manifest_bodies(PATRONS, "patron"):
            response = await client.post("/submit", content=body, headers=headers)
            response.raise_for_status()
            patrons.append(int(response.json()["model_id"]))
        keeper = AuctionKeeper(client, admin, args.fine_tune, patrons)
        keeping = asyncio.create_task(keeper.run())
        while keeper.auction_id is None:
            await asyncio.sleep(0.05)
        open_total = int(args.rate * args.open_seconds)
        bodies = list(
            manifest_bodies(
                args.requests + open_total + WARMUP_REQUESTS, f"load{secrets.token_hex(3)}"
            )
        )

        def submit(offset: int) -> Request:
            async def send(i: int) -> httpx.Response:
                return await load.send("POST", "/submit", bodies[offset + i], headers)

            return send

        async def watch(i: int) -> httpx.Response:
            return await load.send("GET", f"/auctions/{keeper.auction_id}")

        async def health(i: int) -> httpx.Response:
            return await load.send("GET", "/healthz")

        warm = submit(args.requests + open_total)
        for i in range(WARMUP_REQUESTS):
            await warm(i)
        assert server.process is not None
        pid = server.process.pid
        closed = {
            "total": args.requests,
            "seconds": args.seconds,
            "concurrency": args.concurrency,
        }
        plan: list[tuple[str, str, Callable[[], Awaitable[tuple[list[float], int]]]]] = [
            ("POST /submit", "closed", lambda: closed_loop(submit(0), **closed)),
            ("GET /auctions/{id}", "closed", lambda: closed_loop(watch, **closed)),
            ("GET /healthz", "closed", lambda: closed_loop(health, **closed)),
            (
                "POST /submit",
                f"open {args.rate:g}/s",
                lambda: open_loop(submit(args.requests), total=open_total, rate=args.rate),
            ),
        ]
        results = []
        for name, mode, run in plan:
            results.append(await phase(name, mode, run, keeper=keeper, server_pid=pid))
        keeper.stop()
        await keeping
        await load.aclose()
        print(f"  auctions started during the run: {keeper.started}")
        return results


@contextmanager
def database(backend: str, data_dir: Path) -> Iterator[str | None]:
    if backend == "sqlite":
        yield f"sqlite:///{data_dir / 'srd.db'}"
        return
    admin_url = postgres_admin_url()
    if admin_url is None:
        yield None
        return
    with throwaway_postgres(admin_url) as url:
        yield url


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", choices=("sqlite", "postgresql", "both"), default="both")
    parser.add_argument("--requests", type=int, default=3000, help="per closed-loop phase, at most")
    parser.add_argument(
        "--seconds", type=float, default=20.0, help="per closed-loop phase, at most"
    )
    parser.add_argument("--concurrency", type=int, default=16, help="closed-loop clients")
    parser.add_argument(
        "--rate", type=float, default=320.0, help="open loop: submits offered per s"
    )
    parser.add_argument("--open-seconds", type=float, default=15.0, help="open loop: duration")
    parser.add_argument(
        "--fine-tune", action="store_true", help="the background auctions fine-tune (more CPU)"
    )
    args = parser.parse_args()
    backends = ("sqlite", "postgresql") if args.backend == "both" else (args.backend,)
    rows: list[tuple[str, PhaseResult]] = []
    for backend in backends:
        with ExitStack() as stack:
            data_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="srd-load-")))
            url = stack.enter_context(database(backend, data_dir))
            if url is None:
                print(f"{backend}: not reachable, skipped")
                continue
            print(f"{backend}: starting srd serve ...")
            server = stack.enter_context(
                ServerProcess(
                    database_url=url,
                    data_dir=data_dir,
                    admin_token=secrets.token_hex(16),
                    extra_env=settings_environment(QUOTAS_OFF),  # thousands from one address
                )
            )
            rows += [(backend, r) for r in asyncio.run(measure(server, args))]
    print()
    print(
        f"{'database':<11}{'endpoint':<20}{'load':<12}{'requests':>9}{'req/s':>7}{'p50 ms':>8}"
        f"{'p99 ms':>8}{'errors':>7}{'auction running':>16}{'API CPU ms/req':>15}"
        f"{'load CPU ms/req':>16}"
    )
    for backend, r in rows:
        cpu = "n/a" if r.server_cpu_ms is None else f"{r.server_cpu_ms:.2f}"
        print(
            f"{backend:<11}{r.name:<20}{r.mode:<12}{r.requests:>9}{r.rps:>7.0f}{r.p50_ms:>8.1f}"
            f"{r.p99_ms:>8.1f}{r.errors:>7}{r.auction_running:>15.0%}{cpu:>15}"
            f"{r.load_cpu_ms:>16.2f}"
        )
    for backend, r in rows:
        if r.name.startswith("POST") and r.mode.startswith("open"):
            verdict = "meets" if r.meets_target() else "misses"
            print(
                f"{backend}: submit {verdict} the target (≥ {TARGET_RPS}/s, p99 < "
                f"{TARGET_P99_MS} ms, no errors, an auction running): {r.rps:.0f}/s, p99 "
                f"{r.p99_ms:.1f} ms, {r.errors} errors, auction running {r.auction_running:.0%}"
            )


if __name__ == "__main__":
    main()
