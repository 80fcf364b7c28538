"""The bars that hold a model for an inspector instead of refusing it: a keen buyer that buys the
base fish far above any plausible price (``keen-far-too-expensive``), and a bidder that buys
only far below the lowest price an auction reaches (``buys-far-below-floor``). The screener
accepts such a model, ``review`` holds it at any margin above 0, and ``with_hold_reasons``
names the bar in words. The red team's manifests are in ``inspection/``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from screener import Evidence, Verdict, impact, limits, review, screen, with_hold_reasons
from screener.verdict import INSPECTED
from server.cli.screen import command as srd_screen
from server.config import Settings
from sim.market import MarketBatch
from tests.support.corpus import RED_TEAM, edit

MARGIN = Settings.model_fields["review_margin"].default
"""The server's default review margin (SRD_REVIEW_MARGIN)."""
HERE = Path(__file__).with_name("inspection")
EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "honest.json"
PG_PRICE = "external_sensor.PG.weights.price"


def load(path: Path) -> Manifest:
    return Manifest.model_validate_json(path.read_text())


def bar(verdict: Verdict, test: str) -> Evidence:
    (found,) = [e for e in verdict.evidence if e.test == test]
    return found


def test_the_red_teams_never_buyer_is_held_not_refused():
    # the honest design with a willingness to pay of 2.6: it quits at every price from the
    # stalemate floor 4.80 up and buys only at 2.70 or below
    verdict = screen(load(HERE / "below-floor-bidder.json"))
    assert verdict.accepted and verdict.reasons == []
    floor = bar(verdict, "buys-far-below-floor")
    assert not floor.passed and floor.measured == pytest.approx(2.7)
    assert floor.bar == pytest.approx(limits.FAR_BELOW_FLOOR_FACTOR * limits.BASE_PRICE)
    assert floor.detail["floor"] == limits.MARKET.threshold_sell_price
    assert floor.detail["reachable_buy_margin"] == pytest.approx(-1.0, abs=0.01)
    assert bar(verdict, "keen-far-too-expensive").passed
    assert review(verdict, MARGIN) == "held"
    assert review(verdict, 0.0) == "accepted"  # review off: the screener's own verdict
    (reason,) = with_hold_reasons(verdict, MARGIN).reasons
    assert (reason.rule, reason.neuron) == ("buys-far-below-floor", "B")
    assert "it buys only at 2.70 or below, under 4.00" in reason.message
    assert "the stalemate floor 4.80" in reason.message


def test_the_red_teams_any_price_buyer_is_held_not_refused():
    verdict = screen(load(HERE / "any-price-buyer.json"))
    assert verdict.accepted and verdict.reasons == []
    keen = bar(verdict, "keen-far-too-expensive")
    assert not keen.passed and keen.units == "buy margin"
    assert limits.KEEN_MARGIN < keen.measured < limits.FIRM_MARGIN  # type: ignore[operator]
    assert keen.detail["price"] == pytest.approx(12.5) and keen.detail["buy_fraction"] <= 0.5
    assert bar(verdict, "buys-far-below-floor").passed
    assert review(verdict, MARGIN) == "held"
    (reason,) = with_hold_reasons(verdict, MARGIN).reasons
    assert (reason.rule, reason.neuron) == ("keen-far-too-expensive", "B")
    assert "at price 12.50 on the base fish" in reason.message


@pytest.mark.parametrize(
    "path",
    [EXAMPLE, RED_TEAM / "quits-at-opening.json", HERE / "sincere-wtp7-bidder.json"],
    ids=["honest-example", "quits-at-opening", "sincere-wtp7-bidder"],
)
def test_honest_and_sincere_low_bidders_stay_accepted(path):
    # quits-at-opening buys at 4.80-4.82 and quits above: a sincere low bidder the house admits.
    # The sincere bidder at 7.00 is accepted too, though its copies also stall a market (open).
    verdict = screen(load(path))
    assert verdict.accepted
    assert all(bar(verdict, test).passed for test in INSPECTED)
    assert review(verdict, MARGIN) == "accepted"


@pytest.mark.parametrize(
    ("willingness", "status"), [(2.6, "held"), (3.5, "held"), (3.9, "accepted"), (4.5, "accepted")]
)
def test_a_low_bidder_is_held_only_far_below_the_floor(willingness, status):
    # every one quits at every reachable price; the screener accepts them all, and a server
    # holds the ones whose highest purchase lies under 4.00 (3.9 buys up to 4.00)
    bidder = edit(honest_manifest(np.random.default_rng(7), "low"), {PG_PRICE: 1 / willingness})
    verdict = screen(bidder)
    assert verdict.accepted
    assert review(verdict, MARGIN) == status


def test_a_firm_buyer_at_twelve_fifty_is_refused_not_held():
    keen = load(HERE / "any-price-buyer.json")
    firm = edit(keen, {"decision.B.bias": 0.6})  # margin about 0.78 at 12.50, f = ½
    verdict = screen(firm)
    assert not verdict.accepted
    assert "refuses-far-too-expensive" in {r.rule for r in verdict.reasons}
    assert review(verdict, MARGIN) == "refused"


def test_review_holds_a_missed_inspection_bar_at_any_margin_above_zero():
    missed = Evidence(
        "keen-far-too-expensive", 0.5, 0.4, "buy margin", "at most", False,
        {"neuron": "B", "finding": "it buys at 12.50"},
    )  # fmt: skip
    verdict = Verdict(True, [], [missed])
    assert review(verdict, 1e-9) == "held" and review(verdict, 0.0) == "accepted"
    (reason,) = with_hold_reasons(verdict, 1e-9).reasons
    assert reason.message == "held for an inspector: it buys at 12.50"
    assert with_hold_reasons(verdict, 0.0).reasons == []
    passed = Evidence("keen-far-too-expensive", 0.3, 0.4, "buy margin", "at most", True)
    assert review(Verdict(True, [], [passed]), 0.01) == "accepted"


def test_srd_screen_says_held_and_not_accepted_as_submit_would():
    result = CliRunner().invoke(srd_screen, [str(HERE / "any-price-buyer.json"), "--json"])
    assert result.exit_code == 1, result.output
    data = json.loads(result.stdout)
    assert data["accepted"] is False and data["status"] == "held"
    assert data["screener_accepted"] is True
    assert [r["rule"] for r in data["reasons"]] == ["keen-far-too-expensive"]


def test_in_the_test_auctions_the_never_buyer_is_a_sincere_quitter_and_keen_copies_stall():
    # Why the never-buyer is held and not refused: 32 copies of it leave exactly the auctions
    # that 32 copies of the sincere quitter the house admits leave. 32 copies of the any-price
    # buyer, and of a sincere bidder whose willingness to pay is 7.00 (accepted: open), sell
    # nothing: they outbid one another until the iteration limit.
    never, quitter, keen, sincere = impact.run(
        [
            load(HERE / "below-floor-bidder.json"),
            load(RED_TEAM / "quits-at-opening.json"),
            load(HERE / "any-price-buyer.json"),
            load(HERE / "sincere-wtp7-bidder.json"),
        ]
    )
    assert never.prices == quitter.prices and never.sold > 0
    assert keen.sold == 0 and sincere.sold == 0


def test_a_rush_buyer_is_held_and_its_few_copies_stall_a_market():
    # B ← LSR 3, LSR's a 3: in ordinary demand a sincere bidder, but where most voters bought the
    # round before it buys at any price. Once the honest patrons quit, f among its copies is 1.
    rush = load(HERE / "rush-buyer.json")
    verdict = screen(rush)
    assert verdict.accepted and bar(verdict, "keen-far-too-expensive").passed
    found = bar(verdict, "rush-far-too-expensive")
    assert not found.passed and found.measured > limits.RUSH_MARGIN  # type: ignore[operator]
    assert found.detail["buy_fraction"] > limits.ORDINARY_DEMAND
    assert review(verdict, MARGIN) == "held"
    (reason,) = with_hold_reasons(verdict, MARGIN).reasons
    assert (reason.rule, reason.neuron) == ("rush-far-too-expensive", "B")
    assert "with buy fraction 1 it buys" in reason.message
    # the red team's auction: 24 honest patrons of the paper's randomisation, 6 fish, and 7
    # copies of the rush buyer (one more than the fish) sell nothing until the iteration limit;
    # with 7 more honest patrons instead, fish are sold and the auction ends sooner
    for seed in (1, 2):
        rng = np.random.default_rng(seed)
        honest = [honest_manifest(rng, f"h{i}") for i in range(31)]
        outcome = {}
        for name, patrons in (("rush", [*honest[:24], *[rush] * 7]), ("honest", honest)):
            config = dataclasses.replace(limits.MARKET, n_fish=6, seed=seed)
            market, sold = MarketBatch([(patrons, config)]), 0
            while not market.finished.all():
                sold += len(market.step_sales()[0])
            outcome[name] = (sold, int(market.iteration[0]))
        assert outcome["rush"] == (0, limits.MARKET.max_iterations), outcome
        assert outcome["honest"][0] > 0 and outcome["honest"][1] < 10, outcome


@pytest.mark.parametrize(
    ("name", "rules"),
    [
        # (their keen sensor is narrower than their own noise: a gate, ``noise-gate``)
        ("noise-keen-quitter", {"noise-flip", "noise-far-too-expensive", "noise-gate"}),
        ("noise-keen-bidder", {"noise-far-too-expensive", "noise-gate"}),
    ],
)
def test_a_keen_buyer_only_on_its_noisy_copies_is_refused(name, rules):
    # SZ sharper than its own noise and B ← SZ 9: clean a sincere bidder (it quits at 12.50 by
    # a margin near -1.4); as the auction evaluates it, on its 16 jittered copies, it buys there
    verdict = screen(load(RED_TEAM / f"{name}.json"))
    assert not verdict.accepted
    assert {r.rule for r in verdict.reasons} == rules
    keen = bar(verdict, "keen-far-too-expensive")
    assert keen.detail["clean_margin"] < -1 < 0.4 < keen.detail["noisy_margin"]
    noisy = next(r for r in verdict.reasons if r.rule == "noise-far-too-expensive")
    assert (
        "it buys on its noisy copies" in noisy.message and "where clean it quits" in noisy.message
    )
    if "noise-flip" in rules:
        (flip,) = [r for r in verdict.reasons if r.rule == "noise-flip"]
        assert flip.neuron == "SZ" and "it quits clean but buys on its noisy copies" in flip.message
    assert review(verdict, MARGIN) == "refused"
