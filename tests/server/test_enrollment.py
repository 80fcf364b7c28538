"""Enrolling auctions: created with ``enrollment_s``, they stay pending while participants add
their accepted models (``POST /auctions/{id}/patrons``), then play with the patrons they have."""

from __future__ import annotations

import time
from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.support.factories import honest, saboteur, unique
from tests.support.server import ADMIN, wait_for

ENDED = ("finished", "failed", "cancelled")


def submit(client: TestClient, manifest: dict[str, Any]) -> dict[str, Any]:
    answer = client.post("/submit", json=manifest)
    assert answer.status_code == 201, answer.text
    return dict(answer.json())


def join(client: TestClient, auction_id: int, model: dict[str, Any], token: str | None = None):
    headers = {"Authorization": f"Bearer {token or model['token']}"}
    return client.post(
        f"/auctions/{auction_id}/patrons", json={"model_id": model["model_id"]}, headers=headers
    )


def create(client: TestClient, **body: Any) -> int:
    answer = client.post("/auctions", json=body, headers=ADMIN)
    assert answer.status_code == 201, answer.text
    return int(answer.json()["auction_id"])


def ended(client: TestClient, auction_id: int) -> dict[str, Any]:
    return dict(
        wait_for(
            lambda: client.get(f"/auctions/{auction_id}").json(), lambda a: a["status"] in ENDED, 60
        )
    )


def loc_and_type(response: Any) -> tuple[list[Any], str]:
    (item,) = response.json()["detail"]
    return item["loc"], item["type"]


def test_participants_join_while_it_enrolls_then_it_plays_with_them(client: TestClient) -> None:
    models = [submit(client, honest(unique("joins"), seed=100 + i)) for i in range(3)]
    assert all(m["status"] == "accepted" for m in models)
    auction_id = create(client, rarity=0.5, enrollment_s=2.0)
    pending = client.get(f"/auctions/{auction_id}").json()
    assert pending["status"] == "pending" and pending["model_ids"] == []
    assert pending["enroll_until"] is not None

    first = join(client, auction_id, models[0])
    assert first.status_code == 201, first.text
    assert first.json()["position"] == 0 and first.json()["n_patrons"] == 1
    assert join(client, auction_id, models[1]).json()["position"] == 1
    repeat = join(client, auction_id, models[0])
    assert repeat.status_code == 200 and repeat.json()["position"] == 0  # the same answer

    stranger = join(client, auction_id, models[2], token=models[0]["token"])
    assert stranger.status_code == 403
    assert loc_and_type(stranger) == (["header", "Authorization"], "bad_token")
    done = ended(client, auction_id)
    assert done["status"] == "finished", done["error"]
    assert done["model_ids"] == [models[0]["model_id"], models[1]["model_id"]]
    assert done["n_initial"] == 1  # int(0.5 × 2 patrons), counted when the enrollment ended
    assert done["enroll_until"] is None and done["history"]

    late = join(client, auction_id, models[2])
    assert late.status_code == 409
    assert loc_and_type(late) == (["path", "auction_id"], "not_enrolling")


def test_only_accepted_models_join_once_per_participant(client: TestClient) -> None:
    auction_id = create(client, n_fish=1, enrollment_s=30.0)
    refused = client.post("/submit", json=saboteur(unique("joins-sab"))).json()
    assert refused["status"] == "refused"
    answer = join(client, auction_id, refused)
    assert answer.status_code == 409 and loc_and_type(answer) == (["body", "model_id"], "refused")

    name = unique("joins-twice")
    first = submit(client, honest(name, seed=101))
    second = client.post(
        "/submit",
        json=honest(name, seed=102),
        headers={"Authorization": f"Bearer {first['token']}"},
    ).json()
    assert join(client, auction_id, first).status_code == 201
    other_version = join(client, auction_id, {**second, "token": first["token"]})
    assert other_version.status_code == 409
    assert loc_and_type(other_version) == (["body", "model_id"], "same_participant")

    missing = client.post(
        f"/auctions/{auction_id}/patrons",
        json={"model_id": 10**9},
        headers={"Authorization": f"Bearer {first['token']}"},
    )
    assert missing.status_code == 404 and loc_and_type(missing)[0] == ["body", "model_id"]
    no_token = client.post(f"/auctions/{auction_id}/patrons", json={"model_id": first["model_id"]})
    assert no_token.status_code == 401
    cancelled = client.delete(f"/auctions/{auction_id}", headers=ADMIN).json()
    assert cancelled["status"] == "cancelled" and cancelled["enroll_until"] is None
    assert join(client, auction_id, first).status_code == 200  # it had joined: the same answer


def test_an_auction_without_enrollment_takes_no_patrons(client: TestClient) -> None:
    model = submit(client, honest(unique("joins-fixed"), seed=103))
    auction_id = create(client, n_fish=1, model_ids=[model["model_id"]])
    other = submit(client, honest(unique("joins-late"), seed=104))
    answer = join(client, auction_id, other)
    assert answer.status_code == 409
    (item,) = answer.json()["detail"]
    assert item["type"] == "not_enrolling" and "created with enrollment_s" in item["msg"]


@pytest.mark.parametrize(
    ("body", "words"),
    [
        ({"n_fish": 1}, "nobody joined"),
        ({"rarity": 0.1}, "puts no fish on sale"),
    ],
)
def test_an_enrollment_too_thin_fails_the_auction_saying_why(
    client: TestClient, body: dict[str, Any], words: str
) -> None:
    # Submitted (screened) first: a busy machine's screening could outlast the enrollment.
    model = submit(client, honest(unique("joins-thin"), seed=105)) if "rarity" in body else None
    auction_id = create(client, enrollment_s=2.0, **body)
    if model is not None:
        assert join(client, auction_id, model).status_code == 201  # 0.1 × 1 patron: no fish
    started = time.monotonic()
    failed = ended(client, auction_id)
    assert failed["status"] == "failed" and words in failed["error"]
    assert time.monotonic() - started < 30


@pytest.mark.parametrize("value", [-1, 86_401, "60", True, 1e-300, 0.5])
def test_enrollment_s_is_bounded_and_typed(client: TestClient, value: Any) -> None:
    before = len(client.get("/auctions", params={"limit": 100}).json()["items"])
    answer = client.post("/auctions", json={"n_fish": 1, "enrollment_s": value}, headers=ADMIN)
    assert answer.status_code == 422
    assert ["body", "enrollment_s"] in [item["loc"] for item in answer.json()["detail"]]
    assert len(client.get("/auctions", params={"limit": 100}).json()["items"]) == before
