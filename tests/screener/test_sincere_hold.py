"""The sincere-hold rule: on the decisive row, every hold must be backed by a purchase at a
price the auction can still come down to; the reachable prices come from the market's rules."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from agents.batch import from_manifests
from agents.forward import decide
from agents.negotiator import honest_manifest
from screener import limits, screen, screen_many
from screener.probes import FLOOR_INDEX, LOWEST_REACHABLE, SCAN_PRICES, probe
from sim.market import MarketConfig
from tests.support.corpus import edit
from tests.support.screening import message_of, rules_of

PG_PRICE = "external_sensor.PG.weights.price"


def low_price_holder(honest):
    """Declares a willingness to pay of 4.3 (inside the plausible band), holds from there to a
    quit price just above the decisive window: the issue's first disguised saboteur."""
    return edit(
        honest,
        {
            PG_PRICE: 1 / 4.3,
            "external_sensor.PG.activation.a": 10.0,
            "decision.Q.weights.PG": 10.0,
            "decision.Q.bias": -8.6,
            "decision.L.bias": 0.5,
        },
    )


def decisions(manifest, prices, f=0.5):
    rows = torch.tensor([[p, 1, 1, 1, 0.5, 0.5, 0.5, f] for p in prices], dtype=torch.float64)
    return "".join("BHQ"[d] for d in decide(from_manifests([manifest]), rows)[0].tolist())


def test_the_reachable_prices_come_from_the_market_rules():
    market = MarketConfig(n_fish=1)
    assert market == limits.MARKET and market.base_price == limits.BASE_PRICE
    assert (market.base_price, 1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.5) == limits.BASE_ROW
    assert SCAN_PRICES[FLOOR_INDEX] == market.threshold_sell_price
    steps = np.diff(SCAN_PRICES[FLOOR_INDEX:])
    np.testing.assert_allclose(steps, market.decrement)
    top = market.base_price + limits.SCAN_RISES * market.increment
    assert SCAN_PRICES[-1] == pytest.approx(top)
    # up to the base price the auction can still walk down to the floor; above it, a fall of
    # more than increment − decrement ends it (plus the allowed slack)
    slack = limits.HOLD_REACH_SLACK * market.decrement
    at_base = int(np.flatnonzero(np.isclose(SCAN_PRICES, market.base_price))[0])
    assert SCAN_PRICES[LOWEST_REACHABLE[at_base]] == pytest.approx(
        market.threshold_sell_price - slack
    )
    fall = market.increment - market.decrement + slack
    above = at_base + 20
    assert SCAN_PRICES[LOWEST_REACHABLE[above]] == pytest.approx(SCAN_PRICES[above] - fall)


def test_a_low_price_holder_is_refused_with_the_prices_named(honest):
    model = low_price_holder(honest)
    assert decisions(model, [4.8, 5.0, 5.3, 5.5]) == "HHHQ"
    verdict = screen(model)
    assert rules_of(verdict) == {("sincere-hold", "L")}
    message = message_of(verdict, "sincere-hold", "L")
    assert "it holds from 4.80 to 5.3" in message
    assert "4.80 is the stalemate floor, the lowest price it reaches" in message
    assert (
        "it would buy only at 4.60 or below (a purchase up to 0.05 lower still counts)" in message
    )


@pytest.mark.parametrize("willingness", [2.6, 3.5, 4.0, 4.5])
def test_a_sincere_low_bidder_who_quits_above_its_price_is_admitted(honest, willingness):
    bidder = edit(honest, {PG_PRICE: 1 / willingness})
    assert set(decisions(bidder, SCAN_PRICES[FLOOR_INDEX:])) == {"Q"}
    assert not probe(from_manifests([bidder])).holds[0]
    assert screen(bidder).accepted


def test_holding_far_above_the_last_purchase_price_is_refused(honest):
    # Buys up to about 5.05 and holds to 5.45 before quitting: once the price has risen to
    # 5.30, the auction can never come back to 5.05.
    holder = edit(
        honest,
        {
            PG_PRICE: 1 / 5.05,
            "decision.Q.weights.PG": 10.0,
            "decision.Q.bias": -8.6,
            "decision.L.bias": 0.5,
        },
    )
    verdict = screen(holder)
    message = message_of(verdict, "sincere-hold", "L")
    assert "the auction can come down only to" in message
    assert "a fall of more than 0.04 ends the auction)" in message


def test_a_reach_derived_from_other_market_rules(monkeypatch, honest):
    """The rule reads the floor from the market: with a floor of 4.30 the low-price holder buys
    at reachable prices (4.30 and a little above), so its holds up to the base price are backed
    and only those above it, where a rise leaves no way back to 4.30, are refused."""
    import importlib

    import screener.probes as probes

    monkeypatch.setattr(
        limits, "MARKET", dataclasses.replace(limits.MARKET, threshold_sell_price=4.3)
    )
    reloaded = importlib.reload(probes)
    try:
        assert reloaded.SCAN_PRICES[reloaded.FLOOR_INDEX] == pytest.approx(4.3)
        checks = reloaded.probe(from_manifests([low_price_holder(honest)])).checks
        k = checks.rules.index("sincere-hold")
        assert checks.failed[0, k]
        message = checks.message(k, 0)
        assert "at 5.0" in message and "the auction can come down only to 4.9" in message
    finally:
        monkeypatch.undo()
        importlib.reload(probes)


def test_the_honest_factory_is_admitted_and_rarely_holds():
    rng = np.random.default_rng(21)
    models = [honest_manifest(rng, f"h{i}") for i in range(400)]
    verdicts = screen_many(models)
    assert sum(v.accepted for v in verdicts) >= 398
    holds = probe(from_manifests(models)).holds
    assert 0 < holds.mean() < 0.05
