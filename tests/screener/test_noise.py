"""The decisive row as the market sees it: the noise-gated holder family (a sincere bidder on
the clean item, a holder on its own noisy copies) is refused, honest models are not, the
market-impact test runs on models that hold only under noise, and the verdicts are the same
alone and in a batch."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.batch import from_manifests
from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from screener import impact, limits, screen, screen_many
from screener.checks import cheap_checks, failed_any
from screener.noisy import evaluate
from screener.probes import probe
from tests.support.corpus import RED_TEAM, edit
from tests.support.red_team_noise import NOISE_GATED, NoiseGated, noise_gated_holders
from tests.support.screening import message_of

EXAMPLE = Path(__file__).parents[2] / "examples" / "honest.json"


@pytest.fixture(scope="module")
def family() -> dict[str, Manifest]:
    return noise_gated_holders()


def test_the_stored_red_team_files_are_the_family(family):
    for name, manifest in family.items():
        stored = Manifest.model_validate(json.loads((RED_TEAM / f"{name}.json").read_text()))
        assert stored == manifest


def test_the_clean_probes_see_sincere_bidders(family):
    """What the screener saw before: every rule and clean probe passes and the clean scan never
    holds, so the market-impact test never ran."""
    batch = from_manifests(list(family.values()))
    probed = probe(batch)
    assert not probed.holds.any()
    assert not probed.checks.failed.any()
    cheap = cheap_checks(batch)
    clean_groups = cheap.groups[:-1]  # every group but the noisy scan's
    assert not failed_any(clean_groups).any()
    assert cheap.noisy.holds.all()  # the market sees every one of them hold


def test_the_family_is_refused_naming_the_sub_type_neuron(family):
    verdicts = screen_many(list(family.values()))
    for (name, manifest), verdict in zip(family.items(), verdicts, strict=True):
        assert not verdict.accepted, name
        rules = {(r.rule, r.neuron) for r in verdict.reasons}
        assert ("noise-flip", "ST") in rules, name
        message = message_of(verdict, "noise-flip", "ST")
        copies, sigma = manifest.augmentation.copies, manifest.augmentation.noise_std
        assert message.startswith(
            f"evaluated as the auction evaluates it (its {copies} copies jittered by σ {sigma:g}, "
            f"{limits.NOISE_DRAWS} draws), on the auction's decisive row"
        )
        assert "the sub-type neuron ST reads 1.00 on the clean fish and 0." in message
        flip = next(e for e in verdict.evidence if e.test == "noise-flip")
        assert flip.measured is not None and flip.measured > flip.bar
        assert not flip.passed and flip.units == "price"
        assert (
            flip.detail["clean"].startswith("buys 4.75-5.") and "holds" not in flip.detail["clean"]
        )
        assert "holds 4.8" in flip.detail["noisy"] or "holds 4.9" in flip.detail["noisy"]


def test_holds_the_auction_cannot_turn_into_purchases_are_named(family):
    verdict = screen(family["noise-gated-holder-a"])
    message = message_of(verdict, "noise-gated-hold", "ST")
    assert "with buy fraction 0 it holds from 4.8" in message
    assert "on its noisy copies it buys only at 4.8" in message
    gated = next(e for e in verdict.evidence if e.test == "noise-gated-hold")
    assert gated.measured is not None and gated.bar is not None
    assert gated.measured > gated.bar and not gated.passed


def test_the_impact_test_runs_on_what_the_market_sees(monkeypatch):
    """A narrow noise-gated holder (a few cents of holds, only on its noisy copies, each backed
    by a purchase the auction can reach) passes every cheap check; it is run in the test
    auctions because it holds under noise, where the clean scan would have skipped it. (Its
    gate is one ``noise-gate`` refuses: that rule is off here, to see the path a model that
    holds only under noise takes.)"""
    monkeypatch.setattr(limits, "NOISE_GATE_SHIFT", float("inf"))
    model = NoiseGated(4.91, 4.98, 5.10, copies=8, seed=9).build("narrow")
    cheap = cheap_checks(from_manifests([model]))
    assert not failed_any(cheap.groups)[0]
    assert not cheap.probed.holds[0] and cheap.noisy.holds[0]
    refs, wide = impact.references(), impact.wide_references()  # before the spy
    ran: list[int] = []
    real = impact.run

    def spy(candidates, trials=None):
        ran.append(len(candidates))
        return real(candidates, trials)

    monkeypatch.setattr(impact, "run", spy)
    verdict = screen(model)
    (measured,) = [e for e in verdict.evidence if e.test == "market-impact"]
    (outcome,) = real([model])
    if abs(outcome.mean_price - refs.lowest_price) <= limits.IMPACT_WINDOW:  # near the bar:
        assert ran == [1, 1]  # its auctions in more populations too, pooled
        (more,) = real([model], impact.more_trials())
        outcome, refs = impact.pooled(outcome, more), wide
    else:
        assert ran == [1]
    assert measured.measured == pytest.approx(outcome.mean_price)
    assert measured.bar == pytest.approx(refs.lowest_price)
    assert measured.passed == (outcome.mean_price >= refs.lowest_price) == verdict.accepted
    assert measured.detail["without_copies"] == pytest.approx(refs.alone.mean_price)


def test_the_noise_gated_holders_copies_pull_the_price_below_the_bar(family):
    refs = impact.references()
    prices = [o.mean_price for o in impact.run([family[f"noise-gated-holder-{v}"] for v in "abce"])]
    assert all(p < refs.lowest_price for p in prices)
    assert all(refs.saboteurs.mean_price < p for p in prices)


def test_honest_models_do_not_flip_and_are_admitted_at_an_unseen_seed():
    rng = np.random.default_rng(20_261_203)
    models = [honest_manifest(rng, f"unseen-{i}") for i in range(192)]
    noisy = evaluate(from_manifests(models))
    assert noisy.flip.max() < limits.NOISE_FLIP_BAND
    verdicts = []
    for start in range(0, len(models), 64):
        verdicts += screen_many(models[start : start + 64])
    assert sum(v.accepted for v in verdicts) / len(verdicts) >= 0.995


def test_a_verdict_does_not_depend_on_its_batch(family):
    rng = np.random.default_rng(31)
    mixed = [honest_manifest(rng, f"h{i}") for i in range(5)] + list(family.values())[:3]
    together = [v.to_dict() for v in screen_many(mixed)]
    alone = [screen(m).to_dict() for m in mixed]
    assert together == alone
    assert (
        evaluate(from_manifests(mixed)).noisy.tolist()
        == evaluate(from_manifests(mixed)).noisy.tolist()
    )


def test_the_projection_runs_the_auctions_fine_tuning_rounds():
    assert impact.rounds() == limits.MARKET.fine_tune_rounds == 4


def test_variant_numbers_cover_the_issue():
    bands = [(v.hold_from, v.hold_to) for v in NOISE_GATED.values()]
    assert min(a for a, _ in bands) == 4.85 and max(b for _, b in bands) == 5.15
    assert len({v.seed for v in NOISE_GATED.values()}) == len(NOISE_GATED)


def test_scores_that_overflow_get_no_noisy_reason(honest):
    overflow = edit(honest, {"decision.B.bias": 1e308, "decision.B.weights.PG": 1e308})
    noisy = evaluate(from_manifests([overflow]))
    assert not noisy.checks.failed.any() and not noisy.holds.any()
    rules = {r.rule for r in screen(overflow).reasons}
    assert "probe-non-finite" in rules and not rules & {"noise-gated-hold", "noise-flip"}


def test_a_gate_placed_between_the_noisy_scans_buy_fractions_is_read_where_it_peaks():
    """A red team's ST gate peaking at a buy fraction of 0.86 (ST reads the jittered gill at
    √ε = 0.001 and f at the demand-sharpness bound): at the noisy scan's 0.7 and 1 it read 0.3
    and the model was accepted; its copies held at 0.8-0.95. The gate reads every buy fraction
    of the clean scan, and names the one where the noise moves ST most."""
    manifest = Manifest.model_validate_json((RED_TEAM / "f-localized-gill-gate.json").read_text())
    verdict = screen(manifest)
    assert not verdict.accepted
    assert {(r.rule, r.neuron) for r in verdict.reasons} == {("noise-gate", "ST")}
    message = message_of(verdict, "noise-gate", "ST")
    assert "with buy fraction 0.875 and 0.1" in message, message
    assert "moves a decision score by 1.3" in message, message


def test_a_price_gate_edge_sharper_than_its_noise_that_holds_only_on_its_copies_is_a_gate():
    """PG ten times the design's sharpness at σ 0.05, its hold neuron L winning where the copies'
    mean PG lies between 0 and 1 (near the edge, on the copies only; clean it never holds).
    Read on copies whose price is clean, as an edge along the price would seem to allow, it
    was accepted, and its 32 copies did 0.83 of the always-hold saboteur's harm with the
    honest patrons fine-tuning (``tests/support/harm.py``, 8 trials, seed 1): a gate is a gate
    whichever input its noise is on, and honest PGs that sharp at that noise stay refused."""
    document = json.loads(EXAMPLE.read_text())
    document["external_sensor"]["PG"]["activation"]["a"] = 200.0
    document["augmentation"] |= {"noise_std": 0.05, "copies": 5}
    document["decision"]["L"] |= {"weights": {**document["decision"]["L"]["weights"], "PG": 2.0}}
    document["decision"]["L"]["bias"] = -0.3
    document["decision"]["Q"] |= {"weights": {**document["decision"]["Q"]["weights"], "PG": 3.0}}
    document["decision"]["Q"]["bias"] = -1.0
    verdict = screen(Manifest.model_validate(document))
    assert {(r.rule, r.neuron) for r in verdict.reasons} == {("noise-gate", "PG")}
    assert "high-price neuron PG reads" in message_of(verdict, "noise-gate", "PG")
