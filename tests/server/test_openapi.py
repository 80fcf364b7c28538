"""The OpenAPI document states what the service does: the bearer on /submit is optional, an
auction takes exactly one of n_fish or rarity, each job kind has its own params schema with
its bounds, path ids are bounded integers, and fields carry their descriptions."""

from __future__ import annotations

from typing import Any

import jsonschema
import pytest
from fastapi.testclient import TestClient

from sim.experiment import config_fields
from studies.registry import KINDS
from tests.support.openapi import assert_documented
from tests.support.server import ADMIN


@pytest.fixture(scope="module")
def document(client: TestClient) -> dict[str, Any]:
    return dict(client.get("/openapi.json").json())


def test_a_first_submission_and_an_event_stream_need_no_token(
    client: TestClient, document: dict[str, Any]
) -> None:
    for path in ("/submit", "/auctions/{auction_id}/events", "/jobs/{job_id}/events"):
        security = document["paths"][path]["post" if path == "/submit" else "get"]["security"]
        assert {} in security and any("HTTPBearer" in s for s in security), path
    for path, method in (("/models/{model_id}/appeal", "post"), ("/reviews", "get")):
        assert document["paths"][path][method]["security"] == [{"HTTPBearer": []}]  # once
    for path, method in (("/auctions", "post"), ("/jobs", "post"), ("/jobs/{job_id}", "delete")):
        assert {} not in document["paths"][path][method]["security"]


def test_an_auction_takes_exactly_one_supply_option(document: dict[str, Any]) -> None:
    schema = document["components"]["schemas"]["AuctionCreate"]
    assert schema["oneOf"] == [{"required": ["n_fish"]}, {"required": ["rarity"]}]
    assert schema["additionalProperties"] is False
    assert schema["properties"]["model_ids"]["uniqueItems"] is True
    assert "anyOf" not in schema["properties"]["n_fish"]  # null is not a value


def test_each_job_kind_has_its_params_with_bounds(document: dict[str, Any]) -> None:
    alternatives = document["components"]["schemas"]["JobCreate"]["oneOf"]
    by_kind = {a["properties"]["kind"]["const"]: a["properties"]["params"] for a in alternatives}
    assert set(by_kind) == set(KINDS)
    for name, params in by_kind.items():
        assert params["additionalProperties"] is False
        fields = config_fields(KINDS[name].config_class())
        assert set(params["properties"]) == {f.name for f in fields}
        for field in fields:
            assert params["properties"][field.name]["description"] == field.help
    assert by_kind["fish"]["properties"]["steps"]["maximum"] == 10_000_000
    assert by_kind["lavaland"]["properties"]["repeats"]["maximum"] == 100


def test_path_ids_are_bounded_integers(document: dict[str, Any]) -> None:
    (parameter,) = document["paths"]["/jobs/{job_id}"]["get"]["parameters"]
    assert parameter["schema"]["type"] == "integer"
    assert parameter["schema"]["minimum"] == 1 and parameter["schema"]["maximum"] == 2**31 - 1


def test_fields_are_described_by_their_docstrings(document: dict[str, Any]) -> None:
    """A body's fields carry the docstrings written under them as their descriptions."""
    schemas = document["components"]["schemas"]
    vote = schemas["PatronVotePublic"]["properties"]
    assert "server-mode auction" in vote["fine_tuned_after"]["description"]
    weights = schemas["VotedWeightsPublic"]["properties"]["fine_tunings"]
    assert "kept or not" in weights["description"]
    described = [
        name
        for schema in schemas.values()
        for name, field in schema.get("properties", {}).items()
        if field.get("description")
    ]
    assert len(described) >= 40


def test_an_event_streams_errors_are_documented_as_the_json_they_are(
    client: TestClient, document: dict[str, Any]
) -> None:
    """FastAPI gives a route's every answer its media type; an event stream's errors are JSON,
    answered before any stream starts, and the document says so."""
    for route, url in (
        ("/auctions/{auction_id}/events", "/auctions/999999/events"),  # 404
        ("/jobs/{job_id}/events", "/jobs/999999/events?after=AAA"),  # 422, at query.after
    ):
        answer = client.get(url)
        assert answer.status_code in (404, 422), answer.text
        assert answer.headers["content-type"] == "application/json"
        assert_documented(document, route, answer)


def test_what_any_request_may_get_is_documented_for_every_operation(
    client: TestClient, document: dict[str, Any]
) -> None:
    """The per-address rate and share (429), a database or connections unavailable (503), a
    query too long (414), an unreadable or too large body (400, 413, 415) can answer any
    request, so every operation lists them."""
    for path, operations in document["paths"].items():
        for method, operation in operations.items():
            missing = {"400", "413", "414", "415", "429", "503"} - set(operation["responses"])
            assert not missing, (method, path, missing)
    too_long = client.get("/auctions", params={"a": "x" * 9000})
    assert too_long.status_code == 414, too_long.text
    assert_documented(document, "/auctions", too_long)


@pytest.mark.parametrize("path", ["/participants/{name}", "/models"])
def test_a_lookup_by_name_takes_any_name_the_pattern_allows(
    client: TestClient, document: dict[str, Any], path: str
) -> None:
    """Only a new name needs a letter or a digit (``POST /submit``, ``bad_name``): a lookup by
    a name of separators only finds nothing, as the document (which refuses no such name
    there) lets it."""
    url = "/participants/-.-" if path == "/participants/{name}" else "/models?participant=..."
    answer = client.get(url)
    assert answer.status_code == (404 if "{name}" in path else 200), answer.text
    assert_documented(document, path, answer)
    (parameter,) = (p for p in document["paths"][path]["get"]["parameters"]
                    if p["name"] in ("name", "participant"))  # fmt: skip
    alternatives = parameter["schema"].get("anyOf", [parameter["schema"]])  # or null
    assert all("not" not in alternative for alternative in alternatives)
    manifest = document["components"]["schemas"]["Manifest"]["properties"]["participant"]
    assert manifest["not"] == {"pattern": "^[-_.]+$"}


def test_the_cheetah_jobs_options_are_refused_and_taken_as_the_schema_says(
    client: TestClient, document: dict[str, Any]
) -> None:
    """A null stage is no stage (the grid, which takes a backswing): the schema's rule of the
    stages but 4 reads an integer stage only, as the server does."""
    validator = jsonschema.Draft202012Validator(
        {**document["components"]["schemas"]["JobCreate"], "components": document["components"]}
    )
    for stage in ("absent", None, 2, 4):
        for backswing in ("absent", [1.0]):
            options = {"stage": stage, "backswing": backswing, "steps": 20}
            params = {k: v for k, v in options.items() if v != "absent"}
            body = {"kind": "cheetah", "params": params}
            answer = client.post("/jobs", json=body, headers=ADMIN)
            if answer.status_code == 202:
                client.delete(f"/jobs/{answer.json()['job_id']}", headers=ADMIN)
            assert answer.status_code in (202, 422), answer.text
            assert validator.is_valid(body) == (answer.status_code == 202), (params, answer.text)
