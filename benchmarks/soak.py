"""Soak: mixed, bounded load on the HTTP API for a long while (default 10 minutes), on loopback.

One ``srd serve`` on a fresh SQLite file (``--database postgresql`` for the local PostgreSQL).
The load, every class at its own fixed rate (open loop, each request sent at its scheduled
time):

* submissions: new participants, and new versions of participants already registered;
* auctions: one started every ``--auction-every`` seconds among the accepted models, each
  followed to its end;
* jobs: small fish and auction-study jobs every ``--job-every`` seconds, followed to their end;
* reads: GET /healthz, /models/{id}, /auctions/{id}, /jobs/{id};
* bad requests: broken JSON (422), a wrong token (403), a missing model (404) — each must get
  exactly that answer.

Reports per endpoint: requests, p50 and p99 latency, unexpected answers (anything but the
expected status; 0 expected), and the resident memory of every server process (API, screening
process, workers) once warm (after the first population is screened) and at the end of the
load, with the growth bound ``--max-growth-mb``. Exit status 1 when an unexpected answer or more
growth is seen. The load generator shares the machine: "s in all" well above the duration means
it could not keep up with the rates asked for.

Run: ``.venv/bin/python benchmarks/soak.py [--duration 600]``
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
from collections import defaultdict
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # for tests.support

from agents.negotiator import honest_manifest, saboteur_manifest
from server.cli.launch import ServerProcess, settings_environment
from tests.support.databases import postgres_admin_url, throwaway_postgres
from tests.support.server import QUOTAS_OFF

ENDED = {"finished", "failed", "succeeded", "cancelled"}


@dataclass
class Endpoint:
    """Latencies and unexpected answers of one kind of request."""

    latencies_ms: list[float] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)

    def row(self, name: str) -> str:
        lat = sorted(self.latencies_ms) or [float("nan")]
        p99 = lat[min(len(lat) - 1, int(0.99 * len(lat)))]
        return (
            f"| {name} | {len(self.latencies_ms)} | {statistics.median(lat):.1f} | "
            f"{p99:.1f} | {len(self.unexpected)} |"
        )


@dataclass
class Load:
    """The state the load keeps: who is registered, what is accepted, what runs."""

    client: httpx.AsyncClient
    admin: dict[str, str]
    endpoints: dict[str, Endpoint] = field(default_factory=lambda: defaultdict(Endpoint))
    tokens: dict[str, str] = field(default_factory=dict)
    accepted: list[int] = field(default_factory=list)
    auctions: list[int] = field(default_factory=list)
    jobs: list[int] = field(default_factory=list)
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    counter: int = 0

    async def call(
        self, name: str, expected: int, method: str, path: str, **kwargs: Any
    ) -> httpx.Response | None:
        start = time.perf_counter()
        try:
            response = await self.client.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            self.endpoints[name].unexpected.append(f"{type(exc).__name__}: {exc}")
            return None
        self.endpoints[name].latencies_ms.append((time.perf_counter() - start) * 1000)
        if response.status_code != expected:
            self.endpoints[name].unexpected.append(f"{response.status_code}: {response.text[:200]}")
            return None
        return response


async def submit(load: Load) -> None:
    load.counter += 1
    registered = list(load.tokens)
    if registered and load.rng.random() < 0.5:  # a new version of someone registered
        name = registered[int(load.rng.integers(len(registered)))]
        headers = {"Authorization": f"Bearer {load.tokens[name]}"}
    else:
        name, headers = f"soak-{load.counter:06d}", {}
    factory = saboteur_manifest if load.rng.random() < 0.1 else honest_manifest
    manifest = factory(load.rng, name).model_dump(mode="json")
    response = await load.call(
        "POST /submit", 201, "POST", "/submit", json=manifest, headers=headers
    )
    if response is not None:
        body = response.json()
        if body["token"]:
            load.tokens[name] = body["token"]
        if body["accepted"]:
            load.accepted.append(body["model_id"])


async def auction(load: Load) -> None:
    if len(load.accepted) < 8:
        return
    picks = load.rng.choice(len(load.accepted), size=min(32, len(load.accepted)), replace=False)
    ids = sorted({load.accepted[int(i)] for i in picks})
    body = {"n_fish": max(1, len(ids) // 4), "model_ids": ids, "seed": load.counter}
    response = await load.call(
        "POST /auctions", 201, "POST", "/auctions", json=body, headers=load.admin
    )
    if response is not None:
        load.auctions.append(response.json()["auction_id"])


async def job(load: Load) -> None:
    load.counter += 1
    if load.counter % 2:
        body: dict[str, Any] = {"kind": "fish", "params": {"steps": 500, "seed": load.counter}}
    else:
        params = {"rarities": [0.3], "trials": 1, "patrons": 16, "seed": load.counter}
        body = {"kind": "auction-study", "params": params}
    response = await load.call("POST /jobs", 202, "POST", "/jobs", json=body, headers=load.admin)
    if response is not None:
        load.jobs.append(response.json()["job_id"])


async def read(load: Load) -> None:
    await load.call("GET /healthz", 200, "GET", "/healthz")
    if load.accepted:
        model = load.accepted[int(load.rng.integers(len(load.accepted)))]
        await load.call("GET /models/{id}", 200, "GET", f"/models/{model}")
    if load.auctions:
        await load.call("GET /auctions/{id}", 200, "GET", f"/auctions/{load.auctions[-1]}")
    if load.jobs:
        await load.call("GET /jobs/{id}", 200, "GET", f"/jobs/{load.jobs[-1]}")


async def bad(load: Load) -> None:
    json_header = {"Content-Type": "application/json"}
    await load.call(
        "bad: broken JSON", 422, "POST", "/submit", content=b'{"x": ', headers=json_header
    )
    await load.call("bad: missing model", 404, "GET", "/models/2000000000")
    if load.tokens:
        name = next(iter(load.tokens))
        manifest = honest_manifest(load.rng, name).model_dump(mode="json")
        wrong = {"Authorization": "Bearer srdp_wrong"}
        await load.call("bad: wrong token", 403, "POST", "/submit", json=manifest, headers=wrong)


async def every(
    period_s: float, until: float, action: Callable[[Load], Awaitable[None]], load: Load
) -> None:
    """Start ``action`` at a fixed rate until ``until`` (open loop: a slow one does not delay
    the next); wait for the ones in flight at the end."""
    tasks: set[asyncio.Task[None]] = set()
    due = time.monotonic()
    while due < until:
        await asyncio.sleep(max(0.0, due - time.monotonic()))
        task = asyncio.create_task(action(load))
        tasks.add(task)
        task.add_done_callback(tasks.discard)
        due += period_s
    await asyncio.gather(*tasks)


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def processes(root: int) -> dict[int, str]:
    """The server and its child processes: pid → name."""
    found = {root: "api"}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == root:
            found[int(entry.name)] = stat.split("(", 1)[1].split(")", 1)[0]
    return found


def memory(root: int) -> dict[str, float]:
    """Resident memory of the server and its child processes, MB, by ``name[pid]``. Workers
    come and go with their tasks; the API, the screening process and a reused auction worker
    live through the whole load (those alive at both ends are compared)."""
    out = {}
    for pid, name in processes(root).items():
        try:
            out[f"{name}[{pid}]"] = rss_mb(pid)
        except OSError:
            continue
    return out


@contextmanager
def database(kind: str, folder: Path) -> Iterator[str]:
    if kind == "sqlite":
        yield f"sqlite:///{folder / 'srd.db'}"
        return
    admin = postgres_admin_url()
    if admin is None:
        raise SystemExit("PostgreSQL is not reachable on 127.0.0.1:5432")
    with throwaway_postgres(admin) as url:
        yield url


async def soak(
    server: ServerProcess, token: str, args: argparse.Namespace
) -> tuple[Load, dict[str, float]]:
    """Play the load; also return the memory of the server's processes once they are warm
    (after the first population's submissions, which make the screening process load torch)."""
    assert server.process is not None
    limits = httpx.Limits(max_connections=64, max_keepalive_connections=64)
    async with httpx.AsyncClient(base_url=server.url, timeout=60, limits=limits) as client:
        load = Load(client, {"Authorization": f"Bearer {token}"})
        for _ in range(16):  # a population to start from
            await submit(load)
        before = memory(server.process.pid)
        until = time.monotonic() + args.duration
        await asyncio.gather(
            every(1 / args.submit_rate, until, submit, load),
            every(1 / args.read_rate, until, read, load),
            every(args.auction_every, until, auction, load),
            every(args.job_every, until, job, load),
            every(args.bad_every, until, bad, load),
        )
        # everything started must end
        for kind, ids in (("auctions", load.auctions), ("jobs", load.jobs)):
            for item in ids:
                for _ in range(600):
                    state = (await client.get(f"/{kind}/{item}")).json()
                    if state["status"] in ENDED:
                        break
                    await asyncio.sleep(0.5)
                if state["status"] not in ("finished", "succeeded"):
                    load.endpoints[f"{kind} ended"].unexpected.append(f"{item}: {state['status']}")
        return load, before


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=600.0, help="seconds of load")
    parser.add_argument("--database", choices=("sqlite", "postgresql"), default="sqlite")
    parser.add_argument("--submit-rate", type=float, default=5.0, help="submissions per second")
    parser.add_argument("--read-rate", type=float, default=5.0, help="read rounds per second")
    parser.add_argument(
        "--auction-every", type=float, default=10.0, help="seconds between auctions"
    )
    parser.add_argument("--job-every", type=float, default=20.0, help="seconds between jobs")
    parser.add_argument("--bad-every", type=float, default=5.0, help="seconds between bad requests")
    parser.add_argument("--max-growth-mb", type=float, default=150.0, help="RSS growth bound")
    args = parser.parse_args()
    token = secrets.token_hex(16)
    with tempfile.TemporaryDirectory() as tmp, database(args.database, Path(tmp)) as url:
        server = ServerProcess(
            database_url=url,
            data_dir=Path(tmp) / "data",
            admin_token=token,
            extra_env=settings_environment(QUOTAS_OFF),
        )
        with server:
            assert server.process is not None
            started = time.monotonic()
            load, before = asyncio.run(soak(server, token, args))
            elapsed = time.monotonic() - started
            after = memory(server.process.pid)
    print(f"## soak: {args.duration:.0f} s of load on {args.database} ({elapsed:.0f} s in all)\n")
    print("| endpoint | requests | p50 ms | p99 ms | unexpected |\n|---|---|---|---|---|")
    for name in sorted(load.endpoints):
        print(load.endpoints[name].row(name))
    print(
        f"\nauctions started {len(load.auctions)}, jobs {len(load.jobs)}, "
        f"participants {len(load.tokens)}, accepted versions {len(load.accepted)}\n"
    )
    print("| process | RSS when warm MB | RSS at end MB | growth MB |\n|---|---|---|---|")
    grown = []
    for name, mb in before.items():
        if name not in after:
            continue  # a worker that finished its task
        end = after[name]
        grown.append(end - mb)
        print(f"| {name} | {mb:.0f} | {end:.0f} | {end - mb:+.0f} |")
    unexpected = sum(len(e.unexpected) for e in load.endpoints.values())
    for name, endpoint in sorted(load.endpoints.items()):
        for line in endpoint.unexpected[:5]:
            print(f"unexpected {name}: {line}")
    worst = max(grown, default=0.0)
    print(json.dumps({"unexpected": unexpected, "max_growth_mb": round(worst, 1)}))
    if unexpected or worst > args.max_growth_mb:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
