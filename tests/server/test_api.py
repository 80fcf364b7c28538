"""Every route and its error cases, in-process, on SQLite and on the real PostgreSQL."""

from __future__ import annotations

import json
import os
import signal
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from agents.manifest import parse_manifest
from screener import screen
from server.config import Settings
from server.store.tables import Auction, ModelVersion, Participant
from tests.support.factories import honest, saboteur, unique
from tests.support.server import ADMIN, count, locs, wait_for

WRONG = {"Authorization": "Bearer not-the-token"}


def test_healthz_and_openapi(client: TestClient) -> None:
    health = client.get("/healthz").json()
    assert health["status"] == "ok" and health["job_backend"] == "local"
    assert health["screener_populations"] == "public"  # no SRD_SCREENER_SECRET
    assert health["cpus"] == float(len(os.sched_getaffinity(0)))
    paths = client.get("/openapi.json").json()["paths"]
    for path in (
        "/healthz",
        "/submit",
        "/models/{model_id}",
        "/auctions",
        "/auctions/{auction_id}",
        "/jobs",
        "/jobs/{job_id}",
        "/jobs/{job_id}/artifacts/{name}",
    ):
        assert path in paths
    assert client.get("/docs").status_code == 200


def test_unknown_route_and_method_use_the_error_body(client: TestClient) -> None:
    missing = client.get("/nope")
    assert missing.status_code == 404 and locs(missing) == [["path"]]
    wrong_method = client.put("/healthz")
    assert wrong_method.status_code == 405 and locs(wrong_method) == [["method"]]
    assert "PUT is not served at this path, which serves GET, HEAD" in wrong_method.text
    # a body where no route is served is not judged: the route's absence is the answer
    garbage = {"Content-Type": "application/json"}
    assert client.post("/auctions/1", content="garbage", headers=garbage).status_code == 405
    assert client.post("/nope", content="{1", headers=garbage).status_code == 404
    served = client.post("/auctions", content="garbage", headers=garbage)  # judged, before
    assert served.status_code == 422 and locs(served) == [["body"]]  # the token (documented)


def test_submit_new_participant_then_read_model(client: TestClient) -> None:
    name = unique("alice")
    manifest = honest(name, seed=3)
    response = client.post("/submit", json=manifest)
    assert response.status_code == 201, response.text
    body = response.json()
    assert body["participant"] == name and body["version"] == 1
    assert body["accepted"] is True and body["reasons"] == []
    assert body["token"].startswith("srdp_") and len(body["token"]) > 40
    model = client.get(f"/models/{body['model_id']}").json()
    assert model["manifest"] == manifest
    assert (model["participant"], model["version"], model["verdict"]) == (name, 1, "accepted")
    assert model["accepted"] is True and model["reasons"] == []


def test_token_is_stored_hashed_and_never_returned_again(client: TestClient) -> None:
    name = unique("bob")
    first = client.post("/submit", json=honest(name)).json()
    token = first["token"]
    with client.app.state.services.database.session(write=False) as session:  # type: ignore[attr-defined]
        stored = session.scalars(select(Participant).where(Participant.name == name)).one()
    assert token not in stored.token_hash and len(stored.token_hash) == 64
    model = client.get(f"/models/{first['model_id']}").json()
    assert token not in json.dumps(model)


def test_new_version_needs_the_participant_token(client: TestClient) -> None:
    name = unique("carol")
    first = client.post("/submit", json=honest(name, seed=1)).json()
    before = count(client, ModelVersion)

    no_token = client.post("/submit", json=honest(name, seed=2))
    assert no_token.status_code == 401 and locs(no_token) == [["header", "Authorization"]]
    assert no_token.headers["www-authenticate"] == "Bearer"
    wrong = client.post("/submit", json=honest(name, seed=2), headers=WRONG)
    assert wrong.status_code == 403 and locs(wrong) == [["header", "Authorization"]]
    other = client.post("/submit", json=honest(unique("dave"))).json()["token"]
    stolen = client.post(
        "/submit", json=honest(name, seed=2), headers={"Authorization": f"Bearer {other}"}
    )
    assert stolen.status_code == 403
    assert count(client, ModelVersion) == before + 1  # only dave's first version was written

    second = client.post(
        "/submit", json=honest(name, seed=2), headers={"Authorization": f"Bearer {first['token']}"}
    )
    assert second.status_code == 201
    assert second.json()["version"] == 2 and second.json()["token"] is None
    assert second.json()["model_id"] != first["model_id"]


@pytest.mark.parametrize(
    ("mutate", "expected_loc"),
    [
        (
            lambda m: m["external_sensor"]["PG"].pop("bias"),
            ["body", "external_sensor", "PG", "bias"],
        ),
        (
            lambda m: m["decision"]["B"]["weights"].update(PG="x"),
            ["body", "decision", "B", "weights", "PG"],
        ),
        (lambda m: m.update(participant="bad name!"), ["body", "participant"]),
        (lambda m: m.update(surprise=1), ["body", "surprise"]),
        (lambda m: m["fine_tuning"].update(epochs=99), ["body", "fine_tuning", "epochs"]),
    ],
)
def test_submit_invalid_manifest_names_the_field(
    client: TestClient, mutate: Any, expected_loc: list[Any]
) -> None:
    name = unique("eve")
    manifest = honest(name)
    mutate(manifest)
    response = client.post("/submit", json=manifest)
    assert response.status_code == 422
    assert expected_loc in locs(response)
    assert count(client, Participant, name=name) == 0


def test_long_unknown_keys_that_begin_alike_are_each_a_problem(client: TestClient) -> None:
    """Each key is shown by its first 64 characters, and counted whole: five keys alike up
    to their last character are five problems, and 30 are 20 listed and one counting 10."""
    name = unique("keys")
    for n, listed in ((5, 5), (30, 21)):
        manifest = honest(name)
        manifest.update({"k" * 100 + str(i): 1 for i in range(n)})
        response = client.post("/submit", json=manifest)
        assert response.status_code == 422
        detail = response.json()["detail"]
        assert len(detail) == listed, detail
        assert detail[0]["loc"] == ["body", "k" * 64 + "…"]
        if n > 20:
            assert detail[-1]["type"] == "more_problems" and "and 10 more" in detail[-1]["msg"]
    assert count(client, Participant, name=name) == 0


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_submit_non_finite_number_is_refused_with_its_path(
    client: TestClient, literal: str
) -> None:
    name = unique("frank")
    manifest = honest(name)
    manifest["external_sensor"]["SZ"]["bias"] = 12345.5
    raw = json.dumps(manifest).replace("12345.5", literal)
    response = client.post("/submit", content=raw, headers={"Content-Type": "application/json"})
    assert response.status_code == 422
    assert ["body", "external_sensor", "SZ", "bias"] in locs(response)
    assert count(client, Participant, name=name) == 0


def test_a_manifest_whose_sums_overflow_is_refused_and_its_evidence_is_strict_json(
    client: TestClient,
) -> None:
    """A weight at the float's limit is finite, so the manifest parses, but the screener's sums
    overflow: the model is refused (``magnitude``) and stored, and the evidence it overflowed
    reads null, on PostgreSQL too, whose JSON has no infinity (it had been a 500 there)."""
    name = unique("huge")
    manifest = honest(name)
    manifest["decision"]["B"]["weights"]["PG"] = 1.7976931348623157e308
    answer = client.post("/submit", json=manifest)
    assert answer.status_code == 201, answer.text
    assert answer.json()["accepted"] is False
    assert "magnitude" in {r["rule"] for r in answer.json()["reasons"]}
    model = client.get(f"/models/{answer.json()['model_id']}")
    assert model.status_code == 200, model.text

    def no_constant(constant: str) -> None:
        raise AssertionError(f"{constant} is no JSON")

    evidence = json.loads(model.text, parse_constant=no_constant)["evidence"]
    assert any(e["measured"] is None for e in evidence if e["test"].endswith("too-expensive"))


@pytest.mark.parametrize(
    ("raw", "status"), [('{"participant": ', 422), ("[1, 2]", 422), ('"manifest"', 422), ("", 422)]
)
def test_submit_malformed_json_or_wrong_type(client: TestClient, raw: str, status: int) -> None:
    """Text that is not JSON and JSON of the wrong shape are both malformed: 422."""
    response = client.post("/submit", content=raw, headers={"Content-Type": "application/json"})
    assert response.status_code == status
    assert all(loc[0] == "body" for loc in locs(response))


def test_body_over_the_limit_is_413(client: TestClient, settings: Settings) -> None:
    before = count(client, ModelVersion)
    manifest = honest(unique("big"))
    manifest["description"] = "x" * (settings.max_body_bytes + 1)
    response = client.post("/submit", json=manifest)
    assert response.status_code == 413 and locs(response) == [["header", "Content-Length"]]

    def chunks() -> Any:  # no Content-Length: the server must count what arrives
        for _ in range(settings.max_body_bytes // 1024 + 2):
            yield b" " * 1024

    chunked = client.post("/submit", content=chunks(), headers={"Content-Type": "application/json"})
    assert chunked.status_code == 413
    lying = client.post("/submit", content=b"{" + b" " * 100, headers={"Content-Length": "1e9"})
    assert lying.status_code == 400
    assert count(client, ModelVersion) == before


def test_read_model_errors(client: TestClient) -> None:
    missing = client.get("/models/987654321")
    assert missing.status_code == 404 and locs(missing) == [["path", "model_id"]]
    assert client.get("/models/abc").status_code == 422


def test_rejected_model_is_stored_with_reasons_and_never_enters_an_auction(
    client: TestClient,
) -> None:
    name = unique("mallory")
    manifest = saboteur(name)
    expected = screen(parse_manifest(manifest)).to_dict()
    assert expected["accepted"] is False  # the screener turns the always-hold saboteur away
    body = client.post("/submit", json=manifest).json()
    assert body["accepted"] is False and body["reasons"] == expected["reasons"]
    assert {r["rule"] for r in body["reasons"]} >= {"always-holds"}
    model = client.get(f"/models/{body['model_id']}").json()
    assert model["verdict"] == "rejected" and model["reasons"] == expected["reasons"]

    response = client.post(
        "/auctions", json={"n_fish": 1, "model_ids": [body["model_id"]]}, headers=ADMIN
    )
    assert response.status_code == 409 and locs(response) == [["body", "model_ids", 0]]
    assert (
        "rejected (by the screener, or an inspector after it)"
        in response.json()["detail"][0]["msg"]
    )


def test_concurrent_submissions_get_the_screeners_own_verdicts(client: TestClient) -> None:
    """Submissions screened together in one batch get exactly ``screen``'s verdict each."""
    manifests = [(saboteur if i % 3 == 0 else honest)(unique("batch"), seed=i) for i in range(24)]
    with ThreadPoolExecutor(max_workers=12) as pool:
        answers = list(pool.map(lambda m: client.post("/submit", json=m).json(), manifests))
    for manifest, answer in zip(manifests, answers, strict=True):
        expected = screen(parse_manifest(manifest))
        assert answer["accepted"] == expected.accepted
        assert answer["reasons"] == expected.to_dict()["reasons"]


def test_screening_process_is_replaced_when_it_dies(client: TestClient) -> None:
    client.post("/submit", json=honest(unique("warm")))
    screening = client.app.state.services.screening  # type: ignore[attr-defined]
    old = screening.pid()
    os.kill(old, signal.SIGKILL)
    wait_for(lambda: {"pid": screening.pid()}, lambda s: s["pid"] not in (None, old), 30)
    response = client.post("/submit", json=honest(unique("after")))
    assert response.status_code == 201 and response.json()["accepted"] is True


def test_auction_needs_the_admin_token(client: TestClient) -> None:
    assert client.post("/auctions", json={"n_fish": 1}).status_code == 401
    assert client.post("/auctions", json={"n_fish": 1}, headers=WRONG).status_code == 403
    basic = client.post("/auctions", json={"n_fish": 1}, headers={"Authorization": "Basic eDp5"})
    assert basic.status_code == 401
    # The admin token beside another: which one counts would be a guess.
    for pair in ([ADMIN["Authorization"], WRONG["Authorization"]], [WRONG["Authorization"]] * 2):
        headers = [("Authorization", value) for value in pair]
        before = count(client, Auction)
        both = client.post("/auctions", json={"n_fish": 1}, headers=headers)
        assert both.status_code == 400 and locs(both) == [["header", "Authorization"]]
        assert count(client, Auction) == before


@pytest.mark.parametrize(
    ("body", "expected_loc"),
    [
        ({"n_fish": 2, "rarity": 0.5}, ["body", "n_fish"]),
        ({}, ["body", "rarity"]),
        ({"rarity": 0}, ["body", "rarity"]),
        ({"rarity": 1.5}, ["body", "rarity"]),
        ({"n_fish": 0}, ["body", "n_fish"]),
        ({"n_fish": 2, "max_iterations": 0}, ["body", "max_iterations"]),
        ({"n_fish": 2, "model_ids": []}, ["body", "model_ids"]),
        ({"n_fish": 2, "seed": -1}, ["body", "seed"]),
        ({"n_fish": 2, "colour": "red"}, ["body", "colour"]),
    ],
)
def test_create_auction_bad_input(
    client: TestClient, body: dict[str, Any], expected_loc: list[Any]
) -> None:
    client.post("/submit", json=honest(unique("patron")))
    response = client.post("/auctions", json=body, headers=ADMIN)
    assert response.status_code == 422
    assert expected_loc in locs(response)


def test_create_auction_duplicate_and_tiny_rarity(client: TestClient) -> None:
    model_id = client.post("/submit", json=honest(unique("dup"))).json()["model_id"]
    duplicate = client.post(
        "/auctions", json={"n_fish": 1, "model_ids": [model_id, model_id]}, headers=ADMIN
    )
    assert duplicate.status_code == 422
    assert locs(duplicate) == [["body", "model_ids"]]
    unknown = client.post("/auctions", json={"n_fish": 2, "model_ids": [987654321]}, headers=ADMIN)
    assert unknown.status_code == 404 and locs(unknown) == [["body", "model_ids", 0]]
    # Two versions of one participant would give it two votes.
    first = honest(unique("twice"))
    registered = client.post("/submit", json=first).json()
    token = registered["token"]
    again = client.post("/submit", json=first, headers={"Authorization": f"Bearer {token}"})
    assert again.status_code == 201, again.text
    both = [model_id, registered["model_id"], again.json()["model_id"]]
    twice = client.post("/auctions", json={"n_fish": 1, "model_ids": both}, headers=ADMIN)
    assert twice.status_code == 422 and locs(twice) == [["body", "model_ids", 2]]
    assert "takes part once" in twice.text
    tiny = client.post("/auctions", json={"rarity": 0.01, "model_ids": [model_id]}, headers=ADMIN)
    assert tiny.status_code == 409  # the number of patrons puts no fish on sale
    assert locs(tiny) == [["body", "rarity"]]


def test_read_auction_errors(client: TestClient) -> None:
    missing = client.get("/auctions/987654321")
    assert missing.status_code == 404 and locs(missing) == [["path", "auction_id"]]
    assert client.get("/auctions/x").status_code == 422


def test_job_endpoints_need_the_admin_token(client: TestClient) -> None:
    job = {"kind": "fish", "params": {"steps": 10}}
    assert client.post("/jobs", json=job).status_code == 401
    assert client.post("/jobs", json=job, headers=WRONG).status_code == 403
    assert client.delete("/jobs/1").status_code == 401
    assert client.delete("/jobs/1", headers=WRONG).status_code == 403


@pytest.mark.parametrize(
    ("body", "expected_loc"),
    [
        ({"kind": "poker", "params": {}}, ["body", "kind"]),
        ({"params": {}}, ["body", "kind"]),
        ({"kind": "fish", "params": {"steps": 0}}, ["body", "params", "steps"]),
        ({"kind": "fish", "params": {"steps": "many"}}, ["body", "params", "steps"]),
        ({"kind": "fish", "params": {"speed": 3}}, ["body", "params", "speed"]),
        ({"kind": "fish", "params": [1]}, ["body", "params"]),
        ({"kind": "fish", "extra": 1}, ["body", "extra"]),
    ],
)
def test_create_job_bad_input(
    client: TestClient, body: dict[str, Any], expected_loc: list[Any]
) -> None:
    response = client.post("/jobs", json=body, headers=ADMIN)
    assert response.status_code == 422
    assert expected_loc in locs(response)


def test_read_job_and_cancel_errors(client: TestClient) -> None:
    missing = client.get("/jobs/987654321")
    assert missing.status_code == 404 and locs(missing) == [["path", "job_id"]]
    assert client.delete("/jobs/987654321", headers=ADMIN).status_code == 404
    assert client.get("/jobs/987654321/artifacts/result.json").status_code == 404
    assert client.get("/jobs/zz").status_code == 422


def test_non_finite_job_params_are_refused(client: TestClient) -> None:
    raw = '{"kind": "fish", "params": {"steps": NaN}}'
    response = client.post(
        "/jobs", content=raw, headers={**ADMIN, "Content-Type": "application/json"}
    )
    assert response.status_code == 422
    assert ["body", "params", "steps"] in locs(response)


def test_an_unexpected_error_is_a_json_500_that_tells_nothing_of_its_cause(tmp_path) -> None:
    """Whatever goes wrong unforeseen answers the common error body, not a plain-text page."""
    from server.app import create_app
    from tests.support.server import make_settings

    app = create_app(make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data"))

    def boom() -> None:
        raise ZeroDivisionError("a secret detail")

    app.add_api_route("/boom", boom)
    with TestClient(app, raise_server_exceptions=False) as client:
        answer = client.get("/boom")
    assert answer.status_code == 500
    assert answer.headers["content-type"] == "application/json"
    (item,) = answer.json()["detail"]
    assert item["loc"] == ["server"] and item["type"] == "internal_error"
    assert "secret" not in answer.text
    assert answer.headers["x-content-type-options"] == "nosniff"
    assert "default-src 'none'" in answer.headers["content-security-policy"]


def test_requests_that_take_no_body_refuse_one_with_keys_and_take_none_or_empty(
    client: TestClient,
) -> None:
    """A cancel and a token's rotation take no body: a key is refused as every route refuses
    one it does not know, other JSON at the body, nothing done; none or ``{}`` is served."""
    name = unique("bodiless")
    token = client.post("/submit", json=honest(name)).json()["token"]
    rotate = f"/participants/{name}/token"
    owner = {"Authorization": f"Bearer {token}"}
    created = client.post("/auctions", json={"n_fish": 1, "enrollment_s": 3600}, headers=ADMIN)
    cancel = f"/auctions/{created.json()['auction_id']}"
    for path, method, headers in ((rotate, "POST", owner), (cancel, "DELETE", ADMIN)):
        keyed = client.request(method, path, json={"reason": "x", "force": True}, headers=headers)
        assert keyed.status_code == 422, keyed.text
        assert locs(keyed) == [["body", "reason"], ["body", "force"]]
        assert {item["type"] for item in keyed.json()["detail"]} == {"extra_forbidden"}
        listed = client.request(method, path, json=[1], headers=headers)
        assert listed.status_code == 422 and locs(listed) == [["body"]], listed.text
        assert listed.json()["detail"][0]["type"] == "no_body"
    assert client.request("DELETE", cancel, json={"x": 1}).status_code == 401  # the token first
    assert client.get(cancel).json()["status"] == "pending"  # nothing was done
    assert client.post("/submit", json=honest(name), headers=owner).status_code == 201
    rotated = client.post(rotate, json={}, headers=owner)
    assert rotated.status_code == 200, rotated.text
    assert client.delete(cancel, headers=ADMIN).json()["status"] == "cancelled"


def test_a_participant_rotates_its_token_and_the_old_one_is_refused(client: TestClient) -> None:
    """A token that may have leaked is replaced with the participant's own token; a lost one
    with the operator's. The old token is refused from then on, for every request."""
    name = unique("rotates")
    first = client.post("/submit", json=honest(name)).json()["token"]
    path = f"/participants/{name}/token"
    assert client.post(path).status_code == 401
    stranger = client.post("/submit", json=honest(unique("stranger"))).json()["token"]
    refused = client.post(path, headers={"Authorization": f"Bearer {stranger}"})
    assert refused.status_code == 403 and locs(refused) == [["header", "Authorization"]]
    missing = client.post(f"/participants/{unique('nobody')}/token", headers=ADMIN)
    assert missing.status_code == 404 and locs(missing) == [["path", "name"]]
    rotated = client.post(path, headers={"Authorization": f"Bearer {first}"})
    assert rotated.status_code == 200, rotated.text
    second = rotated.json()["token"]
    assert rotated.json()["participant"] == name and second != first
    assert second.startswith("srdp_") and len(second) > 40
    old = client.post("/submit", json=honest(name), headers={"Authorization": f"Bearer {first}"})
    assert old.status_code == 403, old.text
    new = client.post("/submit", json=honest(name), headers={"Authorization": f"Bearer {second}"})
    assert new.status_code == 201 and new.json()["version"] == 2, new.text
    by_operator = client.post(path, headers=ADMIN)  # a participant that lost its token
    third = by_operator.json()["token"]
    for token, status in ((second, 403), (third, 201)):
        again = client.post(
            "/submit", json=honest(name), headers={"Authorization": f"Bearer {token}"}
        )
        assert again.status_code == status, again.text
