"""Loopback load on the HTTP API while auctions run: POST /submit and GET /auctions/{id}.

For each database (SQLite file, and the local PostgreSQL when reachable) it starts ``srd serve``
in a fresh data folder, registers 32 honest patrons, keeps auctions running in the background
(a new one starts whenever the last one ends; ``--fine-tune`` makes them fine-tune), and fires
a bounded number of requests (``--requests``, at most ``--seconds`` per phase) from
``--concurrency`` concurrent httpx clients. Each submit registers a new participant (screening,
token hashing, two inserts, one commit). A last ``GET /healthz`` phase calibrates what the
HTTP stack alone sustains on this machine.

Prints requests/s, p50 and p99 latency, errors, the share of the phase with an auction running,
and the API process's CPU time per request (Linux). Target: ≥ 300 submits/s with p99 < 100 ms.
Load generator, API, screening process, auction worker (and the database server) share the
machine's cores, so the numbers are a floor, and noisy when anything else runs.

Run: ``.venv/bin/python benchmarks/api_load.py [--backend sqlite|postgresql|both]``
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import secrets
import statistics
import tempfile
import time
from collections.abc import Awaitable, Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import torch

from agents.negotiator import honest_manifest
from server.launch import ServerProcess, postgres_admin_url, throwaway_postgres

torch.set_num_threads(1)

PATRONS = 32
WARMUP_REQUESTS = 50
TARGET_RPS = 300
TARGET_P99_MS = 100


@dataclass
class PhaseResult:
    name: str
    requests: int
    errors: int
    seconds: float
    p50_ms: float
    p99_ms: float
    auction_running: float
    server_cpu_ms: float | None
    """CPU time of the API process per request (None where /proc is missing)."""

    @property
    def rps(self) -> float:
        return self.requests / self.seconds


class AuctionKeeper:
    """Keeps one auction running: starts another when the current one has ended."""

    def __init__(self, client: httpx.AsyncClient, admin: dict[str, str], fine_tune: bool) -> None:
        self.client = client
        self.admin = admin
        self.fine_tune = fine_tune
        self.auction_id: int | None = None
        self.running_samples: list[bool] = []
        self.started = 0
        self._stop = asyncio.Event()

    async def run(self) -> None:
        seed = 0
        while not self._stop.is_set():
            if self.auction_id is None or await self._ended(self.auction_id):
                response = await self.client.post(
                    "/auctions",
                    json={"rarity": 0.25, "fine_tune": self.fine_tune, "seed": seed},
                    headers=self.admin,
                )
                response.raise_for_status()
                self.auction_id = int(response.json()["auction_id"])
                self.started += 1
                seed += 1
            await asyncio.sleep(0.05)

    async def _ended(self, auction_id: int) -> bool:
        status = (await self.client.get(f"/auctions/{auction_id}")).json()["status"]
        self.running_samples.append(status == "running")
        return status in ("finished", "failed")

    def stop(self) -> None:
        self._stop.set()


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process (Linux /proc), else None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def load_phase(
    name: str,
    request: Callable[[int], Awaitable[httpx.Response]],
    *,
    total: int,
    seconds: float,
    concurrency: int,
    keeper: AuctionKeeper,
    server_pid: int,
) -> PhaseResult:
    """``total`` requests (or until ``seconds``) from ``concurrency`` workers."""
    latencies: list[float] = []
    errors = 0
    counter = iter(range(total))
    deadline = time.perf_counter() + seconds
    keeper.running_samples.clear()

    async def worker() -> None:
        nonlocal errors
        for i in counter:
            if time.perf_counter() > deadline:
                return
            start = time.perf_counter()
            try:
                response = await request(i)
                ok = response.status_code < 400
            except httpx.HTTPError:
                ok = False
            latencies.append(time.perf_counter() - start)
            errors += not ok

    began, cpu_before = time.perf_counter(), process_cpu_s(server_pid)
    await asyncio.gather(*(worker() for _ in range(concurrency)))
    elapsed, cpu_after = time.perf_counter() - began, process_cpu_s(server_pid)
    ms = sorted(x * 1000 for x in latencies)
    samples = keeper.running_samples or [False]
    return PhaseResult(
        name=name,
        requests=len(ms),
        errors=errors,
        seconds=elapsed,
        p50_ms=statistics.median(ms),
        p99_ms=ms[min(len(ms) - 1, int(0.99 * len(ms)))],
        auction_running=sum(samples) / len(samples),
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


async def measure(server: ServerProcess, args: argparse.Namespace) -> list[PhaseResult]:
    admin = {"Authorization": f"Bearer {server.admin_token}"}
    limits = httpx.Limits(
        max_connections=args.concurrency, max_keepalive_connections=args.concurrency
    )
    async with httpx.AsyncClient(base_url=server.url, limits=limits, timeout=30) as client:
        headers = {"Content-Type": "application/json"}
        for body in manifest_bodies(PATRONS, "patron"):
            response = await client.post("/submit", content=body, headers=headers)
            response.raise_for_status()
        keeper = AuctionKeeper(client, admin, args.fine_tune)
        keeping = asyncio.create_task(keeper.run())
        while keeper.auction_id is None:
            await asyncio.sleep(0.05)
        bodies = list(
            manifest_bodies(args.requests + WARMUP_REQUESTS, f"load{secrets.token_hex(3)}")
        )

        async def submit(i: int) -> httpx.Response:
            return await client.post("/submit", content=bodies[i], headers=headers)

        async def watch(i: int) -> httpx.Response:
            return await client.get(f"/auctions/{keeper.auction_id}")

        async def health(i: int) -> httpx.Response:
            return await client.get("/healthz")

        for i in range(WARMUP_REQUESTS):
            await submit(args.requests + i)
        assert server.process is not None
        pid = server.process.pid
        results = [
            await load_phase(
                name,
                request,
                total=args.requests,
                seconds=args.seconds,
                concurrency=args.concurrency,
                keeper=keeper,
                server_pid=pid,
            )
            for name, request in (
                ("POST /submit", submit),
                ("GET /auctions/{id}", watch),
                ("GET /healthz", health),
            )
        ]
        keeper.stop()
        await keeping
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
    parser.add_argument("--requests", type=int, default=3000, help="per phase, at most")
    parser.add_argument("--seconds", type=float, default=20.0, help="per phase, at most")
    parser.add_argument("--concurrency", type=int, default=16)
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
                    database_url=url, data_dir=data_dir, admin_token=secrets.token_hex(16)
                )
            )
            rows += [(backend, r) for r in asyncio.run(measure(server, args))]
    print()
    print(
        f"{'database':<11}{'endpoint':<21}{'requests':>9}{'req/s':>8}{'p50 ms':>8}"
        f"{'p99 ms':>8}{'errors':>7}{'auction running':>16}{'API CPU ms/req':>16}"
    )
    for backend, r in rows:
        cpu = "n/a" if r.server_cpu_ms is None else f"{r.server_cpu_ms:.2f}"
        print(
            f"{backend:<11}{r.name:<21}{r.requests:>9}{r.rps:>8.0f}{r.p50_ms:>8.1f}"
            f"{r.p99_ms:>8.1f}{r.errors:>7}{r.auction_running:>15.0%}{cpu:>16}"
        )
    for backend, r in rows:
        if r.name.startswith("POST"):
            verdict = "meets" if r.rps >= TARGET_RPS and r.p99_ms < TARGET_P99_MS else "misses"
            print(
                f"{backend}: submit {verdict} the target (≥ {TARGET_RPS}/s, p99 < "
                f"{TARGET_P99_MS} ms)"
            )


if __name__ == "__main__":
    main()
