"""The weight manifest: exact round trips, refusals naming the path, the published schema."""

from __future__ import annotations

import copy
import json
import unicodedata
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.batch import concat, from_manifests, to_manifest
from agents.forward import decide, make_noise
from agents.manifest import (
    SCHEMA_FILE,
    ManifestError,
    manifest_json_schema_text,
    parse_manifest,
    parse_manifest_json,
)
from agents.negotiator import honest_manifest, saboteur_manifest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture
def honest() -> dict:
    return honest_manifest(np.random.default_rng(1), "alice").model_dump(mode="json")


def refusal(data) -> list[dict[str, str]]:
    with pytest.raises(ManifestError) as info:
        parse_manifest(data)
    return info.value.errors


def test_manifest_model_manifest_is_exact():
    rng = np.random.default_rng(12)
    manifests = [honest_manifest(rng, f"h{i}") for i in range(20)]
    manifests += [saboteur_manifest(rng, f"s{i}") for i in range(3)]
    batch = from_manifests(manifests)
    for i, m in enumerate(manifests):
        back = to_manifest(batch, i)
        assert back == m
        assert back.model_dump() == m.model_dump()


def test_concatenated_batches_are_the_batch_of_all_their_manifests():
    """``concat`` of batches (the screener stacks its reference patrons' batch, read once, with
    the candidates') is field for field ``from_manifests`` of the manifests in that order."""
    rng = np.random.default_rng(13)
    first = [honest_manifest(rng, f"h{i}") for i in range(5)]
    second = [saboteur_manifest(rng, "s"), honest_manifest(rng, "h")]
    joined = concat([from_manifests(first), from_manifests(second)])
    whole = from_manifests(first + second)
    for name, value in vars(whole).items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(getattr(joined, name), value), name
            assert getattr(joined, name).dtype == value.dtype, name
        else:
            assert list(getattr(joined, name)) == list(value), name
    with pytest.raises(ValueError, match="at least one batch"):
        concat([])


def test_json_text_round_trip_is_exact(honest):
    m = parse_manifest(honest)
    text = m.model_dump_json()
    again = parse_manifest_json(text)
    assert again == m
    assert again.model_dump_json() == text
    assert parse_manifest(json.loads(text)) == m
    price = again.external_sensor.PG.weights.price
    assert price == honest["external_sensor"]["PG"]["weights"]["price"]  # every bit kept


def test_noiseless_inputs_are_a_set_in_input_order(honest):
    honest["augmentation"]["noiseless_inputs"] = ["st3", "price", "st3"]
    m = parse_manifest(honest)
    assert m.augmentation.noiseless_inputs == ("price", "st3")
    assert to_manifest(from_manifests([m]), 0) == m


MALFORMED = [
    ("missing neuron", lambda d: d["external_sensor"].pop("SZ"), "external_sensor.SZ"),
    (
        "unknown neuron",
        lambda d: d["decision"].__setitem__("SELL", d["decision"]["B"]),
        "decision.SELL",
    ),
    (
        "unknown input",
        lambda d: d["external_sensor"]["PG"]["weights"].__setitem__("colour", 1.0),
        "external_sensor.PG.weights.colour",
    ),
    (
        "missing weight",
        lambda d: d["decision"]["Q"]["weights"].pop("PG"),
        "decision.Q.weights.PG",
    ),
    (
        "weights as an unnamed list",
        lambda d: d["pfc"]["verdict"]["T"].__setitem__("weights", [1.0, 1.0]),
        "pfc.verdict.T.weights",
    ),
    (
        "missing judgement",
        lambda d: d["pfc"]["judgement"].pop("FQ"),
        "pfc.judgement.FQ",
    ),
    (
        "unknown noiseless input",
        lambda d: d["augmentation"].__setitem__("noiseless_inputs", ["st1", "smell"]),
        "augmentation.noiseless_inputs.1",
    ),
    (
        "NaN weight",
        lambda d: d["external_sensor"]["LSR"]["weights"].__setitem__("buy_fraction", float("nan")),
        "external_sensor.LSR.weights.buy_fraction",
    ),
    (
        "infinite bias",
        lambda d: d["decision"]["L"].__setitem__("bias", float("inf")),
        "decision.L.bias",
    ),
    (
        "negative sharpness",
        lambda d: d["external_sensor"]["PG"]["activation"].__setitem__("a", -20.0),
        "external_sensor.PG.activation.a",
    ),
    (
        "unknown activation",
        lambda d: d["external_sensor"]["SZ"].__setitem__("activation", {"kind": "relu"}),
        "external_sensor.SZ.activation",
    ),
    (
        "epsilon out of range",
        lambda d: d["external_sensor"]["ST"]["activation"].__setitem__("epsilon", 0.0),
        "external_sensor.ST.activation.epsilon",
    ),
    (
        "too many copies",
        lambda d: d["augmentation"].__setitem__("copies", 17),
        "augmentation.copies",
    ),
    ("too many epochs", lambda d: d["fine_tuning"].__setitem__("epochs", 11), "fine_tuning.epochs"),
    (
        "batch size zero",
        lambda d: d["fine_tuning"].__setitem__("batch_size", 0),
        "fine_tuning.batch_size",
    ),
    (
        "learning rate above 1",
        lambda d: d["fine_tuning"].__setitem__("learning_rate", 2.0),
        "fine_tuning.learning_rate",
    ),
    ("wrong schema version", lambda d: d.__setitem__("schema_version", 2), "schema_version"),
    ("bad participant", lambda d: d.__setitem__("participant", "a b"), "participant"),
    ("missing pfc", lambda d: d.pop("pfc"), "pfc"),
]


@pytest.mark.parametrize(("case", "edit", "path"), MALFORMED, ids=[c[0] for c in MALFORMED])
def test_malformed_manifests_are_refused_with_their_path(honest, case, edit, path):
    data = copy.deepcopy(honest)
    edit(data)
    errors = refusal(data)
    assert [e["path"] for e in errors] == [path], case
    assert all(e["message"] for e in errors)


def test_non_finite_json_tokens_are_refused_with_their_path(honest):
    text = json.dumps(honest)
    needle = '"bias": 0.0, "activation": {"kind": "threshold", "a": 5.0'
    assert needle in text
    for token in ("NaN", "Infinity", "-Infinity"):
        with pytest.raises(ManifestError) as info:
            parse_manifest_json(text.replace(needle, needle.replace("0.0", token, 1)))
        assert [e["path"] for e in info.value.errors] == ["external_sensor.SZ.bias"]


def test_every_error_is_reported_at_once(honest):
    honest["external_sensor"].pop("ST")
    honest["fine_tuning"]["epochs"] = -1
    paths = {e["path"] for e in refusal(honest)}
    assert paths == {"external_sensor.ST", "fine_tuning.epochs"}


DEFAULT_IGNORABLE = [
    *(0x00AD, 0x034F, 0x061C, 0x115F, 0x1160, 0x17B4, 0x17B5, 0x3164, 0xFEFF, 0xFFA0),
    *range(0x180B, 0x1810), *range(0x200B, 0x2010), *range(0x202A, 0x202F),
    *range(0x2060, 0x2070), *range(0xFE00, 0xFE10), *range(0xFFF0, 0xFFF9),
    *range(0x1BCA0, 0x1BCA4), *range(0x1D173, 0x1D17B), *range(0xE0000, 0xE1000),
]  # fmt: skip
"""Unicode's Default_Ignorable_Code_Point (DerivedCoreProperties.txt): characters a renderer
shows as nothing."""


def test_a_description_shows_what_it_says(honest):
    """Every format character (category Cf) and every default-ignorable one is refused in a
    description, but the joiners and the emoji's presentation selectors, which scripts and
    emoji need, and which are refused in runs of three (a run spells hidden text)."""
    kept = {0x200C, 0x200D, 0xFE0E, 0xFE0F}
    formats = {
        cp for cp in range(0x110000)
        if not 0xD800 <= cp <= 0xDFFF and unicodedata.category(chr(cp)) == "Cf"
    }  # fmt: skip
    for cp in sorted((formats | set(DEFAULT_IGNORABLE)) - kept):
        errors = refusal({**honest, "description": f"a{chr(cp)}b"})
        assert [e["path"] for e in errors] == ["description"], hex(cp)
    for cp in kept:
        assert parse_manifest({**honest, "description": f"a{chr(cp) * 2}b"})
        assert refusal({**honest, "description": f"a{chr(cp) * 3}b"})


def test_published_schema_is_up_to_date():
    assert SCHEMA_FILE.read_text() == manifest_json_schema_text(), (
        "regenerate with: python -m agents.manifest"
    )
    schema = json.loads(SCHEMA_FILE.read_text())
    assert schema["$schema"].endswith("2020-12/schema")
    assert set(schema["required"]) >= {"participant", "external_sensor", "decision", "pfc"}
    assert schema["properties"]["schema_version"]["const"] == 1


def test_examples_parse_and_behave():
    honest_m = parse_manifest_json((EXAMPLES / "honest.json").read_text())
    saboteur = parse_manifest_json((EXAMPLES / "saboteur.json").read_text())
    batch = from_manifests([honest_m, saboteur])
    x = torch.tensor([[p, 1, 1, 1, 0.5, 0.5, 0.5, 0.5] for p in (4.6, 5.5)], dtype=torch.float64)
    decisions = decide(batch, x, make_noise(batch, 2, torch.Generator().manual_seed(0)))
    assert decisions.tolist() == [[0, 2], [1, 1]]  # honest buys cheap, quits dear; saboteur holds
    assert honest_m.fine_tuning.epochs >= 0 and saboteur.fine_tuning.epochs == 0
