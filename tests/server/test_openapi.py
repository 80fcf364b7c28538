"""The OpenAPI document states what the service does: the bearer on /submit is optional, an
auction takes exactly one of n_fish or rarity, each job kind has its own params schema with
its bounds, path ids are bounded integers, and fields carry their descriptions."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient

from sim.experiment import config_fields
from studies.registry import KINDS


@pytest.fixture(scope="module")
def document(client: TestClient) -> dict[str, Any]:
    return dict(client.get("/openapi.json").json())


def test_a_first_submission_needs_no_token(document: dict[str, Any]) -> None:
    security = document["paths"]["/submit"]["post"]["security"]
    assert {} in security and any("HTTPBearer" in s for s in security)
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
