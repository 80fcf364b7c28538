"""The lists (GET /auctions, /models, /jobs), GET /participants/{name}, and what the web view
and the docs are served from; in-process, on SQLite and PostgreSQL."""

from __future__ import annotations

import re
from typing import Any

import pytest
from fastapi.testclient import TestClient

from agents.manifest import DECISIONS, ES_NEURONS, INPUTS, JUDGEMENTS, VERDICTS
from server.api.pages import MAX_PAGE
from server.api.routes.models import DESCRIPTION_PREVIEW
from tests.support.factories import honest, saboteur, unique
from tests.support.server import ADMIN, wait_for

MARKUP_SINKS = re.compile(r"\.(inner|outer)HTML\b|insertAdjacentHTML|document\.write|eval\(")
"""Ways a script could hand a string to the HTML parser (or run it): the page uses none."""


def every_page(client: TestClient, path: str, limit: int, **params: Any) -> list[list[int]]:
    """The ids of each page of a list, following next_cursor to the end."""
    pages: list[list[int]] = []
    query: dict[str, Any] = {"limit": limit, **params}
    while True:
        body = client.get(path, params=query).json()
        pages.append([item["id"] for item in body["items"]])
        if body["next_cursor"] is None:
            return pages
        query["cursor"] = body["next_cursor"]


@pytest.fixture(scope="module")
def population(client: TestClient) -> dict[str, Any]:
    """Two participants with two versions each, a saboteur, and a finished auction."""
    alice, bob, mallory = unique("alice"), unique("bob"), unique("mallory")
    first = client.post("/submit", json=honest(alice, seed=5)).json()
    token = {"Authorization": f"Bearer {first['token']}"}
    second = client.post("/submit", json=honest(alice, seed=2), headers=token).json()
    bob_first = client.post("/submit", json=honest(bob, seed=3)).json()
    bob_token = {"Authorization": f"Bearer {bob_first['token']}"}
    client.post("/submit", json=honest(bob, seed=4), headers=bob_token)
    bad = saboteur(mallory)
    bad["description"] = "x" * 500
    rejected = client.post("/submit", json=bad).json()
    auction_id = client.post(
        "/auctions",
        json={"n_fish": 1, "model_ids": [first["model_id"], bob_first["model_id"]]},
        headers=ADMIN,
    ).json()["auction_id"]
    wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] == "finished",
        timeout_s=120,
    )
    return {
        "alice": alice,
        "bob": bob,
        "mallory": mallory,
        "alice_ids": [first["model_id"], second["model_id"]],
        "rejected": rejected,
        "auction_id": auction_id,
    }


def test_models_list_pages_newest_first_without_gaps(
    client: TestClient, population: dict[str, Any]
) -> None:
    pages = every_page(client, "/models", limit=2)
    ids = [i for page in pages for i in page]
    assert ids == sorted(ids, reverse=True) and len(ids) == len(set(ids))
    assert all(len(page) == 2 for page in pages[:-1]) and 1 <= len(pages[-1]) <= 2
    assert ids == every_page(client, "/models", limit=MAX_PAGE)[0]  # one page: the same rows
    newest = client.get("/models", params={"limit": 1}).json()["items"][0]
    assert newest["id"] == population["rejected"]["model_id"]


def test_models_list_filters_and_fields(client: TestClient, population: dict[str, Any]) -> None:
    alice = client.get("/models", params={"participant": population["alice"]}).json()
    assert [m["id"] for m in alice["items"]] == population["alice_ids"][::-1]
    assert [m["version"] for m in alice["items"]] == [2, 1] and alice["next_cursor"] is None
    rejected = client.get("/models", params={"accepted": "false"}).json()["items"]
    assert rejected and all(m["verdict"] == "rejected" for m in rejected)
    mallory = next(m for m in rejected if m["participant"] == population["mallory"])
    reasons = population["rejected"]["reasons"]
    assert mallory["n_reasons"] == len(reasons)
    assert mallory["rules"] == list(dict.fromkeys(r["rule"] for r in reasons))
    assert len(mallory["description"]) == DESCRIPTION_PREVIEW
    assert mallory["description"].endswith("…")
    accepted = client.get("/models", params={"accepted": "true", "limit": MAX_PAGE}).json()
    assert all(m["accepted"] and m["rules"] == [] for m in accepted["items"])
    nobody = client.get("/models", params={"participant": unique("nobody")}).json()
    assert nobody == {"items": [], "next_cursor": None}
    by_status = {
        status: client.get("/models", params={"status": status, "limit": MAX_PAGE}).json()["items"]
        for status in ("accepted", "refused", "held")
    }
    assert population["mallory"] in {m["participant"] for m in by_status["refused"]}
    assert all(m["status"] == status for status, ms in by_status.items() for m in ms)
    assert by_status["accepted"] and by_status["held"] == []  # this server holds nothing
    for spelling in ("yes", "1", "on", "True"):  # pydantic's lax booleans are not the API's
        refused = client.get("/models", params={"accepted": spelling})
        assert refused.status_code == 422, spelling
        (item,) = refused.json()["detail"]
        assert item["loc"] == ["query", "accepted"] and "true or false" in item["msg"]


@pytest.mark.parametrize(
    ("params", "loc"),
    [
        ({"limit": 0}, ["query", "limit"]),
        ({"limit": MAX_PAGE + 1}, ["query", "limit"]),
        ({"cursor": "not-a-cursor"}, ["query", "cursor"]),
        ({"cursor": 0}, ["query", "cursor"]),
        ({"cursor": 2**31}, ["query", "cursor"]),
        ({"cursor": "1.0"}, ["query", "cursor"]),  # an id, written as path ids are
        ({"limit": "+5"}, ["query", "limit"]),
        ({"participant": "<script>"}, ["query", "participant"]),
        ({"accepted": "maybe"}, ["query", "accepted"]),
        ({"status": "rejected"}, ["query", "status"]),
    ],
)
def test_models_list_bad_parameters_name_themselves(
    client: TestClient, params: dict[str, Any], loc: list[str]
) -> None:
    response = client.get("/models", params=params)
    assert response.status_code == 422
    assert [item["loc"] for item in response.json()["detail"]] == [loc]


def test_any_cursor_is_a_page_below_it(client: TestClient, population: dict[str, Any]) -> None:
    """A cursor is an id: the page holds the rows below it, so every cursor the document
    allows is a valid page, and the next page never repeats a row."""
    first = client.get("/models", params={"limit": 2}).json()
    below = first["next_cursor"]
    assert below == first["items"][-1]["id"]
    after = client.get("/models", params={"limit": 2, "cursor": below}).json()
    assert after["items"] and all(m["id"] < below for m in after["items"])
    far = client.get("/models", params={"cursor": 2**31 - 1}).json()
    assert far["items"][0]["id"] == first["items"][0]["id"]


def test_auctions_list_shows_what_a_person_scans(
    client: TestClient, population: dict[str, Any]
) -> None:
    auction_id = population["auction_id"]
    listed = client.get("/auctions").json()["items"]
    assert [a["id"] for a in listed] == sorted((a["id"] for a in listed), reverse=True)
    item = next(a for a in listed if a["id"] == auction_id)
    full = client.get(f"/auctions/{auction_id}").json()
    assert item["n_patrons"] == 2 and item["status"] == "finished"
    assert item["n_sold"] == len(full["buyers"]) == item["n_initial"] - item["n_available"]
    assert full["n_sold"] == item["n_sold"]  # one name for one figure, in the list and the detail
    assert item["revenue"] == pytest.approx(full["revenue"])
    assert item["iteration"] == len(full["history"])
    assert item["stop_reason"] == full["stop_reason"]
    assert "history" not in item  # a list row stays small whatever the auction's length


def test_jobs_list(client: TestClient) -> None:
    first = client.post("/jobs", json={"kind": "fish", "params": {"steps": 20}}, headers=ADMIN)
    second = client.post("/jobs", json={"kind": "fish", "params": {"steps": 30}}, headers=ADMIN)
    ids = [first.json()["job_id"], second.json()["job_id"]]
    listed = client.get("/jobs", params={"limit": 2}).json()
    assert [j["id"] for j in listed["items"]] == ids[::-1]
    assert listed["items"][0]["params"]["steps"] == 30
    assert set(listed["items"][0]) == {
        "id",
        "kind",
        "status",
        "progress",
        "message",
        "params",
        "created_at",
        "started_at",
        "finished_at",
    }


def test_participant_with_its_versions(client: TestClient, population: dict[str, Any]) -> None:
    body = client.get(f"/participants/{population['alice']}").json()
    assert body["name"] == population["alice"] and body["n_versions"] == 2
    assert [v["id"] for v in body["versions"]] == population["alice_ids"][::-1]
    assert [v["verdict"] for v in body["versions"]] == ["accepted", "accepted"]
    # A name is the same name in other case, as at /submit: the stored spelling answers.
    shouted = client.get(f"/participants/{population['alice'].upper()}").json()
    assert shouted == body
    listed = client.get("/models", params={"participant": population["alice"].upper()}).json()
    assert [v["id"] for v in listed["items"]] == population["alice_ids"][::-1]
    missing = client.get(f"/participants/{unique('nobody')}")
    assert missing.status_code == 404 and missing.json()["detail"][0]["loc"] == ["path", "name"]
    bad = client.get("/participants/a%20b")
    assert bad.status_code == 422 and bad.json()["detail"][0]["loc"] == ["path", "name"]


def test_the_web_view_and_the_docs_are_served_from_the_package(client: TestClient) -> None:
    root = client.get("/", follow_redirects=False)
    page = client.get("/ui/")
    assert root.status_code == 200 and root.content == page.content
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    policy = page.headers["content-security-policy"]
    assert "script-src 'self'" in policy and "default-src 'none'" in policy
    assert "unsafe-inline" not in policy and "<script" not in page.text.split("app.js")[1]
    for asset in ("app.js", "api.js", "dom.js", "auctions.js", "models.js", "jobs.js"):
        script = client.get(f"/ui/{asset}")
        assert script.status_code == 200 and not MARKUP_SINKS.search(script.text)
        assert script.headers["content-type"].startswith("text/javascript")
    assert client.get("/ui/style.css").headers["content-type"].startswith("text/css")
    for path in ("/ui/missing.js", "/ui/..%2Froutes%2Fui.py", "/ui/vendor/..%2F__init__.py"):
        assert client.get(path).status_code == 404
    long_name = client.get(f"/ui/{'A' * 60_000}")  # named by its start, not said back whole
    assert long_name.status_code == 404 and len(long_name.content) < 400, len(long_name.content)
    docs = client.get("/docs").text
    assert "cdn" not in docs.lower() and "/ui/vendor/swagger-ui-bundle.js" in docs
    assert '<html lang="en">' in docs and '<html lang="en">' in client.get("/redoc").text
    assert client.get("/ui/vendor/swagger-ui-bundle.js").status_code == 200
    assert client.get("/ui/vendor/swagger-ui.css").status_code == 200
    redoc = client.get("/redoc").text
    assert "cdn" not in redoc.lower() and "fonts.googleapis" not in redoc
    anatomy = client.get("/ui/neurons.json").json()
    assert anatomy["inputs"] == list(INPUTS) and anatomy["sensor"] == list(ES_NEURONS)
    assert anatomy["decision"] == list(DECISIONS) and anatomy["judgement"] == list(JUDGEMENTS)
    assert anatomy["verdict"] == list(VERDICTS)
    assert set(anatomy["roles"]) == {*ES_NEURONS, *DECISIONS, *JUDGEMENTS, *VERDICTS}
