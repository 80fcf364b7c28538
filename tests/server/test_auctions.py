"""Auctions through the API: the background run, its committed rounds, determinism, defaults."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient

from agents.manifest import parse_manifest
from server.store import crud
from sim.market import Market, MarketConfig
from tests.support.factories import honest, saboteur, unique
from tests.support.server import ADMIN, wait_for

AUCTION_TIMEOUT_S = 120
N_HONEST = 12


def submit_all(client: TestClient, manifests: list[dict[str, Any]]) -> list[int]:
    ids = []
    for manifest in manifests:
        response = client.post("/submit", json=manifest)
        assert response.status_code == 201, response.text
        ids.append(int(response.json()["model_id"]))
    return ids


def run(client: TestClient, body: dict[str, Any]) -> dict[str, Any]:
    response = client.post("/auctions", json=body, headers=ADMIN)
    assert response.status_code == 201, response.text
    auction_id = response.json()["auction_id"]
    return wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] in ("finished", "failed"),
        AUCTION_TIMEOUT_S,
    )


@pytest.fixture(scope="module")
def patrons(client: TestClient) -> tuple[list[dict[str, Any]], list[int]]:
    manifests = [honest(unique("honest"), seed=100 + i) for i in range(N_HONEST)]
    return manifests, submit_all(client, manifests)


def check_consistent(auction: dict[str, Any]) -> None:
    """The committed rounds tell one story: contiguous, chained, each patron counted once."""
    history = auction["history"]
    assert [row["iteration"] for row in history] == list(range(len(history)))
    assert auction["iteration"] == len(history) >= 1
    active = auction["n_patrons"]
    buyers_by_round: dict[int, int] = {}
    for buyer in auction["buyers"]:
        buyers_by_round[buyer["iteration"]] = buyers_by_round.get(buyer["iteration"], 0) + 1
        assert buyer["price"] == history[buyer["iteration"]]["price"]
    quits = auction["quitters"]
    for row, following in zip(history, [*history[1:], None], strict=True):
        assert sum(row["votes"].values()) == active  # every active patron votes on row 0
        left = buyers_by_round.get(row["iteration"], 0)
        assert row["n_available_after"] == row["n_available"] - left
        if following is not None:
            assert following["price"] == row["next_price"]
            assert following["n_available"] == row["n_available_after"]
        active -= left + row["votes"]["quit"]
    buyer_ids = [b["model_id"] for b in auction["buyers"]]
    assert len(set(buyer_ids)) == len(buyer_ids) and len(set(quits)) == len(quits)
    assert not set(buyer_ids) & set(quits)
    assert set(buyer_ids) | set(quits) <= set(auction["model_ids"])
    assert auction["n_available"] == auction["n_initial"] - len(buyer_ids)
    assert auction["price"] == history[-1]["next_price"]
    assert auction["revenue"] == pytest.approx(sum(b["price"] for b in auction["buyers"]))
    sold = len(buyer_ids)  # the paper's purchase rate, and the reference's buyer fraction
    assert auction["purchase_rate"] == pytest.approx(sold / auction["n_initial"])
    assert auction["buyer_fraction"] == pytest.approx(sold / auction["n_patrons"])
    paid = [b["price"] for b in auction["buyers"]]
    assert auction["mean_price"] == (pytest.approx(sum(paid) / sold) if sold else None)
    assert auction["last_price"] == history[-1]["price"]  # `price` is the next one to ask


def test_auction_runs_to_the_end_like_the_market(
    client: TestClient, patrons: tuple[list[dict[str, Any]], list[int]]
) -> None:
    manifests, ids = patrons
    auction = run(client, {"rarity": 0.5, "model_ids": ids, "seed": 7})
    assert auction["status"] == "finished", auction["error"]
    assert auction["n_initial"] == N_HONEST // 2 and auction["n_patrons"] == N_HONEST
    assert auction["model_ids"] == ids and auction["stop_reason"] is not None
    assert auction["participants"] == [m["participant"] for m in manifests]
    assert auction["started_at"] and auction["finished_at"]
    # no fine-tuning: no rounds count to show (it showed the default, 4)
    assert (auction["fine_tune"], auction["fine_tune_rounds"]) == (False, None)
    check_consistent(auction)

    # the same auction played directly on the market gives the very same rounds
    market = Market([parse_manifest(m) for m in manifests], MarketConfig(n_fish=6, seed=7))
    records = list(market.run())
    assert [r["price"] for r in auction["history"]] == [r.price for r in records]
    assert [r["votes"] for r in auction["history"]] == [r.votes for r in records]
    names = [m["participant"] for m in manifests]  # each submitted once: version 1
    assert auction["buyers"] == [
        {
            "model_id": ids[i],
            "price": price,
            "iteration": r.iteration,
            "participant": names[i],
            "version": 1,
            "version_id": ids[i],
        }
        for r in records
        for i, price in r.buyers
    ]
    assert auction["quitters"] == [ids[i] for r in records for i in r.quitters]
    assert auction["quitter_details"] == [
        {
            "model_id": ids[i],
            "participant": names[i],
            "version": 1,
            "iteration": r.iteration,
            "version_id": ids[i],
        }
        for r in records
        for i in r.quitters
    ]
    assert auction["stop_reason"] == records[-1].stop_reason

    # Each participant's page tells how its patron left this auction, as the auction does.
    paid = {b["model_id"]: (b["price"], b["iteration"]) for b in auction["buyers"]}
    left = {q["model_id"]: q["iteration"] for q in auction["quitter_details"]}
    assert paid and left  # the story has both endings to check
    for name, model_id in zip(names, ids, strict=True):
        page = client.get(f"/participants/{name}").json()
        [entry] = [e for e in page["auctions"] if e["auction_id"] == auction["id"]]
        assert (entry["model_id"], entry["bidding_model_id"]) == (model_id, model_id)
        assert entry["auction_status"] == "finished"
        if model_id in paid:
            expected = {
                "outcome": "bought",
                "price": paid[model_id][0],
                "iteration": paid[model_id][1],
            }
        elif model_id in left:
            expected = {"outcome": "quit", "price": None, "iteration": left[model_id]}
        else:
            expected = {"outcome": "stayed", "price": None, "iteration": None}
        assert {k: entry[k] for k in expected} == expected, entry


def test_fine_tuning_auction_with_explicit_fish(
    client: TestClient, patrons: tuple[list[dict[str, Any]], list[int]]
) -> None:
    _, ids = patrons
    auction = run(client, {"n_fish": 3, "model_ids": ids[:8], "fine_tune": True, "seed": 1})
    assert auction["status"] == "finished", auction["error"]
    assert (auction["n_initial"], auction["fine_tune"], auction["rarity"]) == (3, True, None)
    assert (auction["fine_tune_mode"], auction["round_deadline_s"]) == ("server", None)
    assert auction["fine_tune_rounds"] == 4
    check_consistent(auction)


def test_default_patrons_are_the_newest_accepted_version_of_each_participant(
    client: TestClient, patrons: tuple[list[dict[str, Any]], list[int]]
) -> None:
    name = unique("versions")
    first = client.post("/submit", json=honest(name, seed=1)).json()
    token = {"Authorization": f"Bearer {first['token']}"}
    second = client.post("/submit", json=honest(name, seed=2), headers=token).json()
    rejected = client.post("/submit", json=saboteur(name), headers=token).json()
    assert (second["version"], rejected["version"], rejected["accepted"]) == (2, 3, False)
    lone_saboteur = client.post("/submit", json=saboteur(unique("sab"))).json()

    response = client.post("/auctions", json={"n_fish": 1, "seed": 2}, headers=ADMIN)
    assert response.status_code == 201
    auction = client.get(f"/auctions/{response.json()['auction_id']}").json()
    assert auction["status"] in ("pending", "running", "finished")
    assert second["model_id"] in auction["model_ids"]
    for absent in (first, rejected, lone_saboteur):
        assert absent["model_id"] not in auction["model_ids"]
    assert set(patrons[1]) <= set(auction["model_ids"])
    assert [m for m in auction["model_ids"] if m in patrons[1]] == patrons[1]  # participant order
    wait_for(
        lambda: client.get(f"/auctions/{auction['id']}").json(),
        lambda a: a["status"] in ("finished", "failed"),
        AUCTION_TIMEOUT_S,
    )


@pytest.mark.parametrize(
    ("checkpoint", "iteration", "reason"),
    [
        (b"not a checkpoint", 2, "the checkpoint cannot be restored"),
        (None, 3, "3 rounds are committed but no checkpoint is"),
    ],
)
def test_an_auction_that_cannot_resume_is_marked_failed_with_the_reason(
    client: TestClient,
    patrons: tuple[list[dict[str, Any]], list[int]],
    checkpoint: bytes | None,
    iteration: int,
    reason: str,
) -> None:
    """What the runner does at start-up with an unfinished auction whose state is unusable."""
    database = client.app.state.services.database  # type: ignore[attr-defined]
    with database.session(write=True) as session:
        auction = crud.create_auction(
            session,
            model_ids=patrons[1][:4],
            n_fish=2,
            rarity=None,
            max_iterations=64,
            fine_tune=False,
            seed=0,
            opening_price=5.0,
        )
        auction.status, auction.iteration, auction.checkpoint = "running", iteration, checkpoint
        session.commit()
        auction_id = auction.id
    client.app.state.services.auctions.submit(auction_id)  # type: ignore[attr-defined]
    failed = wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] != "running",
        AUCTION_TIMEOUT_S,
    )
    assert failed["status"] == "failed" and failed["finished_at"] is not None
    assert failed["error"].startswith("cannot resume: ") and reason in failed["error"]
