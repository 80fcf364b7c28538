"""What the remote-agent tests check a server's auction against: its replay on the market."""

from __future__ import annotations

from typing import Any

import httpx

from agents.manifest import Manifest, parse_manifest
from server.launch import ServerProcess
from sim.market import Market, MarketConfig


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
