"""Semantic rules: each named weight read against its neuron's meaning, with exact thresholds."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.manifest import parse_manifest
from agents.negotiator import honest_manifest
from screener import screen, screen_many
from screener.probes import probe
from screener.rules import Numbers, semantic_checks
from tests.support.corpus import edit
from tests.support.screening import KNOWN_NEURONS, PROBE_RULES, message_of, rules_of

PG_PRICE = "external_sensor.PG.weights.price"


def test_honest_models_of_the_paper_pass_with_no_reasons():
    rng = np.random.default_rng(0)
    for i in range(20):
        verdict = screen(honest_manifest(rng, f"h{i}"))
        assert verdict.accepted, verdict.reasons
        assert verdict.reasons == []


def test_rule_and_probe_names_are_disjoint_and_cover_the_checks(honest):
    from agents.batch import from_manifests

    batch = from_manifests([honest])
    semantic = {rule for checks in semantic_checks(Numbers.of(batch)) for rule in checks.rules}
    probes = set(probe(batch).checks.rules)
    assert probes == PROBE_RULES
    assert not semantic & probes
    assert len(semantic) >= 20


def test_buy_neuron_liking_high_prices_is_named_in_plain_words(honest):
    verdict = screen(edit(honest, {"decision.B.weights.PG": 0.9}))
    assert not verdict.accepted
    assert message_of(verdict, "decision-sign", "B") == (
        "the buy neuron B has weight +0.9 from PG, the high-price neuron: "
        "this model buys more as the price rises"
    )


def test_a_cut_connection_is_reported_as_cut(honest):
    verdict = screen(edit(honest, {"decision.Q.weights.PG": 0.0}))
    assert message_of(verdict, "decision-sign", "Q") == (
        "the quit neuron Q has no weight from PG, the high-price neuron: "
        "the connection its meaning relies on is cut"
    )


def test_a_weak_designed_connection_is_too_weak(honest):
    verdict = screen(edit(honest, {"pfc.verdict.T.weights.BC": 0.05}))
    assert "too weak to carry its meaning (at least 0.1 in size, sign +)" in message_of(
        verdict, "verdict-sign", "T"
    )
    assert screen(edit(honest, {"pfc.verdict.T.weights.BC": 0.2})).accepted


@pytest.mark.parametrize(
    ("declared", "inside"), [(2.4, False), (2.6, True), (9.8, True), (10.3, False), (50, False)]
)
def test_willingness_to_pay_band_is_half_to_twice_the_base_price(honest, declared, inside):
    # PG crosses c = 1 where p/b = 1 + 0.001 (the δ seeds on the base fish: −3δ + 2δ).
    verdict = screen(edit(honest, {PG_PRICE: 1.0 / declared}))
    assert (("willingness-to-pay", "PG") in rules_of(verdict)) is not inside
    if not inside:
        message = message_of(verdict, "willingness-to-pay", "PG")
        assert f"at price {declared * 1.001:.2f} on the base fish" in message
        assert "outside the plausible 2.50 to 10.00" in message


@pytest.mark.parametrize("weight", [1e300, np.finfo(np.float64).max])
def test_an_absurd_price_weight_declares_an_implausible_willingness_to_pay(honest, weight):
    """The largest float too: PG's point on the base fish was inf − inf there, and no reason
    named its willingness to pay."""
    verdict = screen(edit(honest, {PG_PRICE: float(weight)}))
    assert not verdict.accepted
    assert "outside the plausible 2.50 to 10.00" in message_of(verdict, "willingness-to-pay", "PG")


def test_price_weight_must_be_positive(honest):
    verdict = screen(edit(honest, {PG_PRICE: -0.2}))
    assert ("rises-with-price", "PG") in rules_of(verdict)
    assert ("willingness-to-pay", "PG") not in rules_of(verdict)  # undefined, not reported


def test_better_fish_may_not_look_dearer_beyond_one_price_step(honest):
    # drop = w_length · 0.4 · b with b in [4.8, 5]: 0.02 → ≤ 0.04 (passes), 0.04 → ≥ 0.077.
    assert ("falls-with-quality", "PG") not in rules_of(
        screen(edit(honest, {"external_sensor.PG.weights.length": 0.02}))
    )
    verdict = screen(edit(honest, {"external_sensor.PG.weights.length": 0.04}))
    message = message_of(verdict, "falls-with-quality", "PG")
    assert message.startswith("PG has weight +0.04 from the length: a better fish looks dearer")


def test_activation_kinds_follow_the_meaning(honest):
    changed = edit(
        honest,
        {
            "external_sensor.PG.activation": {"kind": "selective", "epsilon": 1e-4},
            "external_sensor.ST.activation": {"kind": "threshold", "a": 5.0, "c": 0.0,
                                              "negative_slope": 0.01},
        },
    )  # fmt: skip
    found = rules_of(screen(changed))
    assert {("activation-kind", "PG"), ("activation-kind", "ST")} <= found
    assert ("activation-kind", "SZ") not in found


def test_subtype_neuron_must_peak_at_the_preferred_subtype(honest):
    verdict = screen(edit(honest, {"external_sensor.ST.bias": 0.5}))
    assert "at the preferred (½, ½, ½)" in message_of(verdict, "selective-peak", "ST")
    wide = screen(edit(honest, {"external_sensor.ST.activation.epsilon": 0.5}))
    assert {("selective-peak", "ST"), ("selective-width", "ST")} <= rules_of(wide)
    assert screen(edit(honest, {"external_sensor.ST.activation.epsilon": 1e-3})).accepted


def test_size_and_rush_reference_points(honest):
    # SZ crosses c = 1 at (1 − bias − seeds)/1: bias −0.6 → size ≈ 1.59, outside 0.5 to 1.5.
    verdict = screen(edit(honest, {"external_sensor.SZ.bias": -0.6}))
    assert "at size 1.59" in message_of(verdict, "size-reference", "SZ")
    rush = screen(edit(honest, {"external_sensor.LSR.bias": -0.7}))
    assert "at buy fraction 1.19" in message_of(rush, "demand-reference", "LSR")


def test_sharpness_within_a_factor_ten_of_the_design(honest):
    flat = screen(edit(honest, {"external_sensor.LSR.activation.a": 0.05}))
    assert "nearly flat" in message_of(flat, "sharpness", "LSR")
    step = screen(edit(honest, {"external_sensor.SZ.activation.a": 60.0}))
    assert "a hidden step" in message_of(step, "sharpness", "SZ")
    assert screen(edit(honest, {"external_sensor.PG.activation.a": 40.0})).accepted
    # Just past a bound, the reason tells the value from the bound ("10.5", not "10").
    past = screen(edit(honest, {"external_sensor.LSR.activation.a": 10.5}))
    assert "by 10.5 per unit of buy fraction (design 1; allowed 0.1 to 10)" in message_of(
        past, "sharpness", "LSR"
    )


def test_a_model_set_at_a_sharpness_bound_stays_in_after_its_own_fine_tuning():
    """Fine-tuning moves a model set at a bound just past it (float noise for LSR, up to 1%
    for SZ, whose weights train): about half of such honest models were refused for
    ``fine-tuning-drift``."""
    rng = np.random.default_rng(21)

    def size_gain(m: Any) -> float:
        weights = m.external_sensor.SZ.weights
        return float(weights.length + weights.weight)

    edits: dict[str, Any] = {
        "LSR 10": lambda m: {"external_sensor.LSR.activation.a": 10.0},
        "LSR 0.1": lambda m: {"external_sensor.LSR.activation.a": 0.1},
        "SZ 50": lambda m: {"external_sensor.SZ.activation.a": 50.0 / size_gain(m)},
    }
    for name, change in edits.items():
        drawn = [honest_manifest(rng, f"h{i}") for i in range(20)]
        verdicts = screen_many([edit(m, change(m)) for m in drawn])
        refused = [v.reasons[0].message for v in verdicts if not v.accepted]
        assert len(refused) <= 1, (name, refused)


def test_a_neuron_reading_an_input_it_is_not_named_after(honest):
    verdict = screen(edit(honest, {"external_sensor.SZ.weights.price": 0.1}))
    # influence 0.1 · 10 (price span) against (0.5 + 0.5) · 0.4 (size span) = 2.5
    assert "from the price, moving it 2.50× as much as the length and the weight" in message_of(
        verdict, "off-design-input", "SZ"
    )


def test_buying_is_the_default_intent(honest):
    verdict = screen(edit(honest, {"decision.B.bias": 0.3, "decision.L.bias": 0.4}))
    assert message_of(verdict, "buy-intent", "B").startswith(
        "the buy neuron B has bias +0.3, not above the hold neuron L (+0.4)"
    )


def test_a_lying_pfc_is_refused_on_every_verdict_connection(honest):
    swapped = edit(
        honest,
        {
            "pfc.verdict.T.weights": {"PGL": 0.0, "BC": 0.0, "FQ": 1.0},
            "pfc.verdict.F.weights": {"PGL": 1.0, "BC": 1.0, "FQ": 0.0},
        },
    )
    verdict = screen(swapped)
    assert {("verdict-sign", "T"), ("verdict-sign", "F")} <= rules_of(verdict)
    assert sum(r.rule == "verdict-sign" for r in verdict.reasons) == 6
    assert any("judges a false quit to be right" in r.message for r in verdict.reasons)


def test_pfc_judgements_and_biases(honest):
    verdict = screen(edit(honest, {"pfc.judgement.PGL.weights.B": 0.5}))
    assert "it is not about B" in message_of(verdict, "judgement-off-design", "PGL")
    assert ("judgement-bias", "FQ") in rules_of(
        screen(edit(honest, {"pfc.judgement.FQ.bias": 0.4}))
    )
    prior = screen(edit(honest, {"pfc.verdict.F.bias": 1.0}))
    assert "calls every decision wrong" in message_of(prior, "verdict-bias", "T")


def test_augmentation_and_fine_tuning_settings(honest):
    noisy = screen(edit(honest, {"augmentation.noise_std": 0.3}))
    assert ("augmentation-noise", "PG") in rules_of(noisy)
    jittered = screen(edit(honest, {"augmentation.noiseless_inputs": []}))
    assert ("augmentation-subtypes", "ST") in rules_of(jittered)
    quiet = edit(honest, {"augmentation.noiseless_inputs": [], "augmentation.noise_std": 0.0})
    assert screen(quiet).accepted
    for settings in ({"learning_rate": 0.5}, {"epochs": 6}):
        reckless = edit(honest, {"fine_tuning": settings})
        assert ("fine-tuning", "T") in rules_of(screen(reckless))


def test_fine_tuning_that_takes_too_many_steps_a_round_is_refused_at_once(honest):
    """Epochs × ⌈64 rows / batch size⌉ SGD steps a round at most 64 (twice the paper's 32): 4
    epochs at batch 1 with 16 noisy copies and a learning rate too small to move anything had
    been accepted after 7 times the screening of the paper's largest settings, and would
    cost every auction it entered as much."""
    costly = {"epochs": 4, "batch_size": 1, "learning_rate": 1e-7}
    verdict = screen(edit(honest, {"fine_tuning": costly, "augmentation.copies": 16}))
    assert not verdict.accepted
    assert message_of(verdict, "fine-tuning-steps", "T").startswith(
        "fine-tuning takes 256 SGD steps a round (4 epochs at batch size 1 over 64 item rows; "
        "at most 64)"
    )
    for settings in ({"epochs": 4, "batch_size": 4}, {"epochs": 1, "batch_size": 1}):
        within = screen(edit(honest, {"fine_tuning": {**settings, "learning_rate": 1e-5}}))
        assert ("fine-tuning-steps", "T") not in rules_of(within)


def test_gigantic_numbers_are_refused_by_name(honest):
    verdict = screen(edit(honest, {"decision.B.bias": 1e4}))
    assert message_of(verdict, "magnitude", "B") == (
        "the buy neuron B has bias +1e+04, beyond ±10: a gigantic number hides its real effect"
    )
    centre = screen(edit(honest, {"external_sensor.LSR.activation.c": 40.0}))
    assert "threshold centre c +40" in message_of(centre, "magnitude", "LSR")


def test_every_reason_names_a_known_neuron(honest):
    edits = [
        {"decision.B.weights.PG": 0.9},
        {"augmentation.noise_std": 0.3},
        {"fine_tuning": {"learning_rate": 0.5}},
        {"pfc.verdict.F.bias": 2.0},
        {PG_PRICE: 0.02},
    ]
    for changes in edits:
        verdict = screen(edit(honest, changes))
        assert not verdict.accepted
        assert {r.neuron for r in verdict.reasons} <= KNOWN_NEURONS
        assert all(r.message for r in verdict.reasons)


@pytest.mark.parametrize(
    "changes",
    [
        {"external_sensor.PG.weights.price": 5e-324},
        {"external_sensor.PG.weights.st1": 1e308},
        {"external_sensor.LSR.weights.buy_fraction": 5e-324},
        {"external_sensor.SZ.weights.buy_fraction": 1e16},
    ],
)
def test_absurd_weights_are_refused_in_readable_words(honest, changes) -> None:
    """Weights far outside the design (a fuzzer's finds) are refused, and every reason still
    reads as words and short numbers: no "inf", "nan" or 300-digit number in a message."""
    verdict = screen(edit(honest, changes))
    assert not verdict.accepted
    for reason in verdict.reasons:
        words = reason.message.lower()
        assert "inf" not in words.replace("infer", "") and "nan" not in words, reason
        assert not re.search(r"\d{12}", reason.message), reason


def _absurd(data: Any, sign: list[float]) -> None:
    """Every weight and bias of ``data`` set to ±1e308 in turn (``sign`` carries the turn)."""
    if isinstance(data, dict):
        for key, value in data.items():
            if key in ("weights", "bias") and isinstance(value, dict):
                for name in value:
                    sign[0] = -sign[0]
                    value[name] = sign[0] * 1e308
            elif key == "bias" and isinstance(value, float):
                sign[0] = -sign[0]
                data[key] = sign[0] * 1e308
            else:
                _absurd(value, sign)


def test_absurd_weights_get_the_same_reasons_alone_and_in_a_batch(honest) -> None:
    """A fuzzer's find: every weight ±1e308 in turn. Screened alone or among honest models,
    the model gets the same reasons, word for word."""
    data = honest.model_dump(mode="json")
    _absurd(data, [1.0])
    absurd = parse_manifest(data)
    others = [honest_manifest(np.random.default_rng(i), f"h{i}") for i in range(5)]
    alone = screen(absurd)
    batched = screen_many([*others, absurd])[-1]
    assert not alone.accepted
    assert [r.to_dict() for r in batched.reasons] == [r.to_dict() for r in alone.reasons]


@pytest.mark.parametrize("name", ["copy-order-holder", "zero-margin-any-price-buyer"])
def test_a_vote_that_rests_on_the_last_bits_of_the_arithmetic_is_refused(name: str):
    """Buy and hold tie to 1e-16 at every price: one such model bought when screened alone and
    held in the market's full blocks of 16 voters (its 16 copies averaged in another order);
    the other buys everywhere by a hair. Both are refused by ``knife-edge``, saying where."""
    path = Path(__file__).parents[1] / "support" / "red_team" / f"{name}.json"
    verdict = screen(parse_manifest(json.loads(path.read_text())))
    assert not verdict.accepted
    assert ("knife-edge", "B") in rules_of(verdict)
    words = message_of(verdict, "knife-edge", "B")
    assert re.search(r"its two leading scores lie [0-9.e-]+ apart \(on \d+ probed items\)", words)
    assert "within 1e-09" in words and "rests on the last bits" in words
