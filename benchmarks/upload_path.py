"""The API's upload path alone, in one quiet process: what an upload's own code costs.

``benchmarks/capacity.py`` measures a whole server under load, where an upload's CPU mixes with
the transport, the pushes, the auction steps and the other requests, and where the code runs
with cold caches between the agents' processes. This measures the path of
``server.auctions.uploads.upload`` (the strict parse, the checks and the store in one
transaction, the verdict recorded in another, the round made due when its last upload is
judged) in one process that does nothing else, over and over on the same data, so it is the
best case of that code: compare it with the design's floor (``benchmarks/upload_floor.py``)
and with the server under load.

Setup (unmeasured): a real ``srd serve`` on a SQLite file takes 64 honest submissions and plays
a remote auction of them until its first fine-tuning round opens, then stops. Each run restores
that database and uploads every asked patron's pre-built fine-tuned manifest (as the capacity
benchmark's agents do) through ``upload``, with a stand-in screener that accepts at once (the
screener's cost is its own). CPU of the whole process (the thread pool's database work
included) per upload, best of ``--repeats`` runs.

``--disturb`` puts back one thing a server under load does to this code: ``memory`` sweeps
32 MB between two uploads (the caches are cold again, as after the other processes' turn on
the cores), ``thread`` keeps another thread of the process running Python (as the event loop
does while the thread pool writes; the two take turns on the GIL).

    .venv/bin/python benchmarks/upload_path.py [--repeats 5] [--disturb memory|thread]
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import sys
import tempfile
import threading
import time
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import capacity

from agents.manifest import Manifest
from screener import Verdict
from server.api.errors import RequestError
from server.auctions.arrivals import Arrivals
from server.auctions.uploads import UploadRequest, upload
from server.cli.launch import ServerProcess, settings_environment
from server.store.db import Database

PATRONS = 64
DEADLINE_S = 300.0


class Accepting:
    """The screener's stand-in: every fine-tuned version accepted at once."""

    async def verdict(
        self, manifest: Manifest, *, at_the_door: bool = True, manifest_json: str | None = None
    ) -> Verdict:
        return Verdict(accepted=True)


def prepare(folder: Path) -> tuple[int, list[tuple[int, str, bytes]], datetime]:
    """A database whose remote auction has its first round open: the auction, each patron's
    (model id, token, first upload), and a moment inside the round."""
    plan = capacity.Plan(3, 4, DEADLINE_S, (1.0, 5.0), 0)
    url = f"sqlite:///{folder / 'srd.db'}"
    with ServerProcess(
        database_url=url,
        data_dir=folder / "data",
        admin_token=capacity.ADMIN_TOKEN,
        extra_env=settings_environment({**capacity.QUOTAS_OFF}),
        log_path=folder / "serve.log",
    ) as server:
        auction_id, agents, opened = asyncio.run(_open_round(server.url, plan))
    shutil.copy(folder / "srd.db", folder / "round-open.db")
    patrons = [(model_id, token, uploads[0]) for model_id, token, uploads in agents]
    return auction_id, patrons, opened


async def _open_round(
    server: str, plan: capacity.Plan
) -> tuple[int, list[tuple[int, str, list[bytes]]], datetime]:
    admin = {"Authorization": f"Bearer {capacity.ADMIN_TOKEN}"}
    async with httpx.AsyncClient(timeout=60) as client:
        agents = await capacity.submit_agents(client, server, PATRONS, 7, plan)
        body = {
            "n_fish": 6,
            "model_ids": [model_id for model_id, _, _ in agents],
            "fine_tune_mode": "remote",
            "fine_tune_rounds": plan.rounds,
            "max_iterations": plan.iterations,
            "round_deadline_s": plan.deadline_s,
            "seed": 1,
        }
        created = capacity.checked(
            await client.post(f"{server}/auctions", json=body, headers=admin)
        )
        auction_id = created.json()["auction_id"]
        current = await client.get(
            f"{server}/auctions/{auction_id}/rounds/current", params={"wait": 30, "after": 0}
        )
        round_ = capacity.checked(current).json()
    if round_.get("round") != 1 or round_.get("status") != "open":
        raise RuntimeError(f"the first round did not open: {round_}")
    deadline = datetime.fromisoformat(round_["deadline"].replace("Z", "+00:00"))
    return auction_id, agents, deadline - timedelta(seconds=DEADLINE_S - 1)


def run_once(
    folder: Path,
    auction_id: int,
    patrons: list[tuple[int, str, bytes]],
    arrived: datetime,
    disturb: str | None = None,
) -> tuple[int, float]:
    """Every patron's upload on a fresh copy of the database: (uploads answered, CPU s of the
    upload path)."""
    for suffix in ("", "-wal", "-shm"):
        (folder / f"work.db{suffix}").unlink(missing_ok=True)
    shutil.copy(folder / "round-open.db", folder / "work.db")
    database = Database(f"sqlite:///{folder / 'work.db'}")
    stop, spun = threading.Event(), [0.0]
    spinner = threading.Thread(target=_spin, args=(stop, spun), daemon=True)
    if disturb == "thread":
        spinner.start()
        while not spun[0]:  # running before the uploads start
            time.sleep(0.001)
    try:
        return asyncio.run(
            _upload_all(database, auction_id, patrons, arrived, disturb == "memory", spun)
        )
    finally:
        stop.set()
        database.close()


def _spin(stop: threading.Event, spun: list[float]) -> None:
    """Python running in another thread until ``stop``; its CPU time so far in ``spun[0]``."""
    while not stop.is_set():
        sum(range(2000))
        spun[0] = time.thread_time()


SWEPT = np.ones(4_000_000)
"""32 MB, more than the caches hold."""


async def _upload_all(
    database: Database,
    auction_id: int,
    patrons: list[tuple[int, str, bytes]],
    arrived: datetime,
    sweep: bool,
    spun: list[float],
) -> tuple[int, float]:
    """(uploads answered, CPU s of the upload path: the sweeps and the busy thread's own CPU
    left out)."""
    screening: Any = Accepting()
    arrivals = Arrivals()
    answered = 0
    swept = 0.0
    start, spun_before = time.process_time(), spun[0]
    for model_id, token, body in patrons:
        if sweep:  # not counted
            before = time.process_time()
            SWEPT[::8] += 1.0
            swept += time.process_time() - before
        request = UploadRequest(auction_id, 1, model_id, token, body, arrived)
        try:
            await upload(
                database, screening, lambda _: None, request, margin=0.0, arrivals=arrivals
            )
        except RequestError as exc:  # not asked: it left the auction before the round
            if not any(item["type"] == "not_asked" for item in exc.items):
                raise
            continue
        answered += 1
    return answered, time.process_time() - start - swept - (spun[0] - spun_before)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--disturb", choices=("memory", "thread"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="srd-upload-path-") as name:
        folder = Path(name)
        auction_id, patrons, arrived = prepare(folder)
        run_once(folder, auction_id, patrons, arrived)  # warm-up
        runs = [
            run_once(folder, auction_id, patrons, arrived, args.disturb)
            for _ in range(args.repeats)
        ]
        answered, best = runs[0][0], min(cpu for _, cpu in runs)
        print(
            f"{answered} uploads of {len(patrons)} patrons (the others left before the round); "
            f"CPU per upload, best of {args.repeats} runs"
            f"{f' (disturbed: {args.disturb})' if args.disturb else ''}: "
            f"{best / answered * 1e3:.3f} ms"
        )


if __name__ == "__main__":
    main()
