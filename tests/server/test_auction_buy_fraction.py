"""The market's buy-fraction rule through the API: ``POST /auctions`` takes ``buy_fraction``,
``GET /auctions/{id}`` shows it, and the worker plays the auction under it."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient

from agents.manifest import parse_manifest
from sim.market import Market, MarketConfig
from tests.support.factories import honest, unique
from tests.support.server import ADMIN, wait_for

AUCTION_TIMEOUT_S = 120


@pytest.fixture(scope="module")
def patrons(client: TestClient) -> tuple[list[dict[str, Any]], list[int]]:
    manifests = [honest(unique("rule"), seed=300 + i) for i in range(12)]
    ids = []
    for manifest in manifests:
        response = client.post("/submit", json=manifest)
        assert response.status_code == 201, response.text
        ids.append(int(response.json()["model_id"]))
    return manifests, ids


def play(client: TestClient, body: dict[str, Any]) -> dict[str, Any]:
    response = client.post("/auctions", json=body, headers=ADMIN)
    assert response.status_code == 201, response.text
    auction_id = response.json()["auction_id"]
    return wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] in ("finished", "failed"),
        AUCTION_TIMEOUT_S,
    )


def rounds(records: list[Any]) -> list[tuple[float, dict[str, int]]]:
    return [(r.price, r.votes) for r in records]


@pytest.mark.postgres_in_slow_run
def test_each_rule_is_stored_shown_and_played(client: TestClient, patrons) -> None:
    manifests, ids = patrons
    models = [parse_manifest(m) for m in manifests]
    expected = {
        rule: list(Market(models, MarketConfig(n_fish=3, seed=1, buy_fraction=rule)).run())
        for rule in ("all", "staying")
    }
    assert rounds(expected["all"]) != rounds(expected["staying"])  # the rule matters here
    for rule, body in (("all", {}), ("staying", {"buy_fraction": "staying"})):
        auction = play(client, {"n_fish": 3, "model_ids": ids, "seed": 1, **body})
        assert auction["status"] == "finished", auction["error"]
        assert auction["buy_fraction"] == rule
        history = [(row["price"], row["votes"]) for row in auction["history"]]
        assert history == rounds(expected[rule]), rule
        assert auction["stop_reason"] == expected[rule][-1].stop_reason


def test_an_unknown_rule_is_a_422_naming_the_field(client: TestClient, patrons) -> None:
    _, ids = patrons
    for value in ("buyers", None, 1):
        response = client.post(
            "/auctions", json={"n_fish": 1, "model_ids": ids, "buy_fraction": value}, headers=ADMIN
        )
        assert response.status_code == 422, response.text
        assert any(item["loc"] == ["body", "buy_fraction"] for item in response.json()["detail"])


def test_the_rule_is_in_the_published_schema(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()["components"]["schemas"]
    create = schema["AuctionCreate"]["properties"]["buy_fraction"]
    assert create["enum"] == ["all", "staying"] and create["default"] == "all"
    assert "buy_fraction" in schema["AuctionPublic"]["properties"]
