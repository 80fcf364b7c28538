"""``srd screen FILE [--json]``: exit 0 accepted, 1 rejected, 2 unreadable or malformed."""

from __future__ import annotations

import json

import numpy as np
import pytest
import typer
from click.testing import CliRunner

import server.cli.screen  # noqa: F401  (registers the command)
from agents.negotiator import honest_manifest, saboteur_manifest
from server.cli import app


@pytest.fixture(scope="module")
def srd():
    group = typer.main.get_group(app)

    def run(*args: str):
        return CliRunner().invoke(group, ["screen", *args])

    return run


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_accepted_manifest_exits_0_with_one_json_object(srd, tmp_path):
    manifest = honest_manifest(np.random.default_rng(0), "alice")
    outcome = srd(write(tmp_path, "a.json", manifest.model_dump_json()), "--json")
    assert outcome.exit_code == 0, outcome.output
    (line,) = outcome.stdout.strip().splitlines()
    assert json.loads(line) == {"accepted": True, "reasons": []}


def test_rejected_manifest_exits_1_with_reasons(srd, tmp_path):
    manifest = saboteur_manifest(np.random.default_rng(0), "mallory")
    path = write(tmp_path, "s.json", manifest.model_dump_json())
    outcome = srd(path, "--json")
    assert outcome.exit_code == 1
    result = json.loads(outcome.stdout)
    assert result["accepted"] is False
    assert {"rule": "always-holds", "neuron": "L"} in [
        {"rule": r["rule"], "neuron": r["neuron"]} for r in result["reasons"]
    ]
    assert all(set(r) == {"rule", "neuron", "message"} for r in result["reasons"])
    human = srd(path)
    assert human.exit_code == 1
    assert human.stdout.startswith("mallory: rejected")
    assert "L (decisive-row): on the auction's decisive row" in human.stdout


def test_non_finite_number_is_malformed_and_names_its_path(srd, tmp_path):
    data = json.loads(honest_manifest(np.random.default_rng(0), "nan").model_dump_json())
    data["external_sensor"]["PG"]["weights"]["price"] = float("nan")
    outcome = srd(write(tmp_path, "nan.json", json.dumps(data)), "--json")  # writes NaN
    assert outcome.exit_code == 2
    assert "external_sensor.PG.weights.price" in outcome.stderr
    result = json.loads(outcome.stdout)
    assert result["accepted"] is False and result["reasons"] == []
    assert [e["path"] for e in result["errors"]] == ["external_sensor.PG.weights.price"]


def test_missing_fields_and_broken_json_are_malformed(srd, tmp_path):
    data = json.loads(honest_manifest(np.random.default_rng(0), "x").model_dump_json())
    del data["decision"]["L"]
    outcome = srd(write(tmp_path, "m.json", json.dumps(data)))
    assert outcome.exit_code == 2
    assert "decision.L: Field required" in outcome.stderr
    broken = srd(write(tmp_path, "b.json", '{"participant": '))
    assert broken.exit_code == 2
    assert "$: Invalid JSON" in broken.stderr


def test_unreadable_file_exits_2(srd, tmp_path):
    outcome = srd(str(tmp_path / "missing.json"), "--json")
    assert outcome.exit_code == 2
    assert "cannot read" in json.loads(outcome.stdout)["errors"][0]["message"]
