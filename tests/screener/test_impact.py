"""The market-impact test: counterfactual auctions of the batched engine, judged against the same
auctions without the copies, with always-hold saboteurs and with quitters."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from agents.batch import from_manifests
from agents.manifest import parse_manifest
from agents.negotiator import honest_manifest
from screener import impact, limits, screen, screen_many
from screener.checks import cheap_checks, passes_cheap
from screener.probes import probe
from tests.support.corpus import Labelled, red_team_corpus
from tests.support.screening import message_of, rules_of


def red_team(name: str) -> Labelled:
    (entry,) = [e for e in red_team_corpus() if e.construction == f"red-team:{name}"]
    return entry


def test_references_are_cached_and_the_saboteurs_pull_the_price_down():
    refs = impact.references()
    assert impact.references() is refs
    assert refs.saboteurs.mean_price < refs.quitters.mean_price <= refs.alone.mean_price
    assert refs.saboteurs.sold - refs.saboteurs.honest == 0  # saboteurs never buy
    assert refs.saboteurs.mean_price < refs.lowest_price < refs.quitters.mean_price
    share = (refs.quitters.mean_price - refs.lowest_price) / (
        refs.quitters.mean_price - refs.saboteurs.mean_price
    )
    assert abs(share - limits.IMPACT_SHARE) < 1e-9


def test_each_price_names_its_supply_and_scarce_fish_sell_dearer():
    refs = impact.references()
    alone = refs.alone
    assert len(alone.supplies) == len(alone.prices)
    assert set(alone.supplies) == set(limits.IMPACT_SUPPLIES)
    per_supply = [alone.mean_price_at(r) for r in limits.IMPACT_SUPPLIES]
    assert per_supply == sorted(per_supply, reverse=True)  # fewer fish, higher price
    counts = [alone.supplies.count(r) for r in limits.IMPACT_SUPPLIES]
    weighted = sum(c * m for c, m in zip(counts, per_supply, strict=True)) / sum(counts)
    assert abs(weighted - alone.mean_price) < 1e-9
    # the always-hold saboteurs pull the price down at every supply
    for r in limits.IMPACT_SUPPLIES:
        assert refs.saboteurs.mean_price_at(r) < alone.mean_price_at(r)
    assert np.isnan(alone.mean_price_at(0.9))  # no test auction at that supply


def test_the_test_auctions_follow_the_market_rules():
    assert len(impact.TEST_AUCTIONS) == len(limits.IMPACT_SUPPLIES) * limits.IMPACT_TRIALS
    patrons = limits.IMPACT_HONEST + limits.IMPACT_COPIES
    for _, config in impact.TEST_AUCTIONS:
        assert config.base_price == limits.MARKET.base_price
        assert config.threshold_sell_price == limits.MARKET.threshold_sell_price
        assert not config.fine_tune and not config.evaluate_all_rows
    assert {c.n_fish for _, c in impact.TEST_AUCTIONS} == {
        int(r * patrons) for r in limits.IMPACT_SUPPLIES
    }


def test_a_model_holding_just_above_the_opening_price_is_refused_in_numbers():
    """Found by the red team: it buys up to 4.99, holds from 5.00 to 5.04 and quits above, so
    every hold is a few cents from a purchase (the sincere-hold rule admits it), yet 32 copies
    take 0.6 of the saboteurs' harm from an auction of 32 honest patrons."""
    model = red_team("opening-price-holder").manifest
    assert passes_cheap(from_manifests([model]))[0]
    assert probe(from_manifests([model])).holds[0]
    verdict = screen(model)
    assert ("market-impact", "L") in rules_of(verdict)
    # Its copies land within a cent and a half of the first bar: it meets the second stage's
    # populations too and is judged on its 96 auctions against the 96 auctions' references.
    (first,) = impact.run([model])
    assert abs(first.mean_price - impact.references().lowest_price) <= limits.IMPACT_WINDOW
    refs = impact.wide_references()
    (more,) = impact.run([model], impact.more_trials())
    outcome = impact.pooled(first, more)
    assert outcome.mean_price < refs.lowest_price
    message = message_of(verdict, "market-impact", "L")
    assert message.startswith(
        "in 96 test auctions (32 honest patrons, supplies 0.1 to 0.4), 32 copies of this model "
        f"lowered the mean purchase price from {refs.alone.mean_price:.2f} (without them) to "
        f"{outcome.mean_price:.4f}, below the {refs.lowest_price:.4f} allowed"  # cents alike
    )
    assert "they bought 0 of the" in message


def test_models_that_never_hold_are_not_run_in_test_auctions(monkeypatch):
    ran: list[int] = []
    real = impact.run

    def spy(candidates, trials=None):
        ran.append(len(candidates))
        return real(candidates, trials)

    monkeypatch.setattr(impact, "run", spy)
    rng = np.random.default_rng(4)
    models = [honest_manifest(rng, f"h{i}", fine_tune=False) for i in range(16)]
    holders = cheap_checks(from_manifests(models)).holds
    verdicts = screen_many(models)
    assert all(v.accepted for v in verdicts)
    assert ran == ([int(holders.sum())] if holders.any() else [])


def test_projection_reverts_what_the_rules_refuse_and_leaves_the_rest_moving():
    rng = np.random.default_rng(8)
    models = [honest_manifest(rng, f"h{i}") for i in range(6)]
    moving = [m for m in models if m.fine_tuning.epochs > 0]
    batch = from_manifests(moving)
    tuned = impact.project(batch)
    assert passes_cheap(tuned).all()
    assert not torch.equal(tuned.fc_weight, batch.fc_weight)  # honest fine-tuning is kept
    frozen = from_manifests([m for m in models if m.fine_tuning.epochs == 0])
    assert torch.equal(impact.project(frozen).es_weight, frozen.es_weight)


def test_a_judge_that_drifts_the_model_into_holding_is_refused_at_the_door():
    """Found by the red team: honest sensor and decision, a PFC within the rules' limits; its
    own SRD fine-tuning (lr 8e-4, 4 epochs) makes it a holder after one round."""
    model = red_team("drifting-judge").manifest
    assert passes_cheap(from_manifests([model]))[0]
    assert not probe(from_manifests([model])).holds[0]
    verdict = screen(model)
    message = message_of(verdict, "fine-tuning-drift", "T")
    assert message.startswith(
        f"after {impact.rounds()} rounds of its own fine-tuning in a reference auction (lr "
        "0.000802, 4 epochs, batch 6), its PFC's verdicts T/F have made it fail"
    )
    # re-screening inside an auction judges each round's version as it is: no projection
    assert screener_rescreen(model)


def screener_rescreen(model) -> bool:
    from screener import rescreen

    return bool(rescreen(from_manifests([model]))[0])


def test_models_near_the_bar_meet_more_populations_and_the_window_holder_is_refused():
    """Four reference populations admitted every opening-window holder (a hard bargainer: it
    holds from 5.00 to about 5.05, each hold backed by a purchase a cent below). Near the bar the
    test now adds twenty more and judges the 96 auctions: holder b, whose copies landed 0.0008
    above the first bar, is refused; a model whose copies land far above it meets 16."""
    path = Path(__file__).parents[2] / "examples" / "red_team" / "opening-window-holder-b.json"
    holder = parse_manifest(json.loads(path.read_text()))
    verdict = screen(holder)
    (evidence,) = [e for e in verdict.evidence if e.test == "market-impact"]
    (first,) = impact.run([holder])
    assert 0 <= first.mean_price - impact.references().lowest_price <= limits.IMPACT_WINDOW
    assert evidence.detail["test_auctions"] == 96 and not evidence.passed
    assert evidence.bar == impact.wide_references().lowest_price
    assert ("market-impact", "L") in rules_of(verdict) and not verdict.accepted
    honest = [honest_manifest(np.random.default_rng(s), f"h{s}") for s in range(40)]
    tested = [e for v in screen_many(honest) for e in v.evidence if e.test == "market-impact"]
    bar = impact.references().lowest_price
    far = [e for e in tested if e.measured is None or abs(e.measured - bar) > limits.IMPACT_WINDOW]
    assert far and all(e.detail["test_auctions"] == 16 for e in far)
