"""What the remote-agent tests share: agents in subprocesses (``srd agents`` and a stalling
agent of the Python API), and what a server's auction is checked against: its replay on the
market."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import httpx

from agents.manifest import Manifest, parse_manifest
from server.cli.launch import ServerProcess, srd_command
from sim.market import Market, MarketConfig
from tests.support.factories import honest, unique
from tests.support.server import wait_for

STALLING_AGENT = r"""
import asyncio, sys, time
import httpx, numpy as np
from agents.negotiator import honest_manifest
from agents.remote import Client, RemoteAgent, faithful_fine_tune

server, name, transport, stall_round, stall_s = sys.argv[1:6]

def stall(manifest, info):
    if info.round == int(stall_round):
        print("stalling", info.round, flush=True)
        time.sleep(float(stall_s))
    return faithful_fine_tune(manifest, info)

async def main():
    async with httpx.AsyncClient(base_url=server) as http:
        manifest = honest_manifest(np.random.default_rng(100), name)
        agent = RemoteAgent(Client(http), manifest, fine_tuner=stall, transport=transport)
        await agent.submit()
        print("model", agent.model_id, flush=True)
        while not (found := await agent.auctions()):
            await asyncio.sleep(0.2)
        await agent.play(found[0])
        print("uploads", agent.uploads.accepted + agent.uploads.refused, flush=True)

asyncio.run(main())
"""
"""An agent (the Python API) that submits, waits for its auction and plays it, sleeping in its
fine-tuning of one round. Its seed, 100, makes a patron that pays up to 4.97 and stays in the
auction past iteration 1. It prints ``model <id>``, ``stalling <round>`` and at the end
``uploads <n>``."""


def stalling_agent(
    server: ServerProcess, name: str, transport: str, stall_round: int, stall_s: float
) -> subprocess.Popen[str]:
    """``STALLING_AGENT`` in a subprocess (stdout piped)."""
    stall = (str(stall_round), str(stall_s))
    return subprocess.Popen(
        [sys.executable, "-c", STALLING_AGENT, server.url, name, transport, *stall],
        stdout=subprocess.PIPE,
        text=True,
        cwd=Path(__file__).parents[2],
    )


def agents_process(
    server: ServerProcess, prefix: str, *options: str, transport: str = "http"
) -> subprocess.Popen[str]:
    """``srd agents --json`` against the server in a subprocess (stdout and stderr piped),
    its participants named ``<prefix>-...``, waiting up to 120 s for their auction."""
    fixed = ("--wait", "120", "--transport", transport, "--json")
    return subprocess.Popen(
        [
            *srd_command(),
            "agents",
            "--server",
            server.url,
            "--name-prefix",
            prefix,
            *fixed,
            *options,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def stored_manifest(server: ServerProcess, model_id: int) -> Manifest:
    """The manifest of a stored model version, as ``GET /models/{id}`` gives it."""
    response = httpx.get(f"{server.url}/models/{model_id}", timeout=30)
    response.raise_for_status()
    return parse_manifest(response.json()["manifest"])


def replay(
    server: ServerProcess, auction: dict[str, Any], config: MarketConfig
) -> list[dict[str, Any]]:
    """The auction replayed on the market from its entry models, applying in each round the
    versions the server accepted: its records as the server shows its history."""
    entries = [stored_manifest(server, i) for i in auction["model_ids"]]
    market = Market(entries, config)
    rounds = {r["iteration"]: r for r in auction["fine_tuning"]}
    history = []
    while not market.finished:
        record = market.step()
        history.append(
            {
                "iteration": record.iteration,
                "price": record.price,
                "n_available": record.n_available,
                "votes": record.votes,
                "row_votes": record.row_votes,
                "next_price": record.next_price,
                "n_available_after": record.n_available_after,
            }
        )
        if market.pending_round is not None:
            answers = rounds[record.iteration]["answers"]
            market.apply_round(
                {
                    auction["model_ids"].index(a["model_id"]): stored_manifest(
                        server, a["version_id"]
                    )
                    for a in answers
                    if a["outcome"] == "accepted" and a["uploaded_id"] is not None
                }
            )
    return history


def next_round(
    server: ServerProcess, auction_id: int, after: int, timeout_s: float
) -> dict[str, Any]:
    """The auction's next open round above ``after`` (long-polled), or its end."""
    return wait_for(
        lambda: httpx.get(
            f"{server.url}/auctions/{auction_id}/rounds/current",
            params={"wait": 5, "after": after},
            timeout=30,
        ).json(),
        lambda r: (
            (r["status"] == "open" and r["round"] > after)
            or r["auction_status"] not in ("pending", "running")
        ),
        timeout_s,
    )


def honest_remote_auction(
    server: ServerProcess, seeds: Sequence[int], *, name: str, **settings: Any
) -> tuple[int, list[tuple[int, str, dict[str, Any]]]]:
    """A remote auction (created with the server's operator token) of one honest model per
    seed, each submitted by its own participant: its id, and each patron's (model id, token,
    manifest), in order. ``settings`` go into the ``POST /auctions`` body."""
    entered = []
    admin = {"Authorization": f"Bearer {server.admin_token}"}
    with httpx.Client(base_url=server.url, timeout=30) as http:
        for seed in seeds:
            manifest = honest(unique(name), seed=seed)
            answer = http.post("/submit", json=manifest).raise_for_status().json()
            entered.append((answer["model_id"], answer["token"], manifest))
        body = {"model_ids": [model_id for model_id, _, _ in entered],
                "fine_tune_mode": "remote", **settings}  # fmt: skip
        created = http.post("/auctions", json=body, headers=admin)
        assert created.status_code == 201, created.text
    return int(created.json()["auction_id"]), entered
