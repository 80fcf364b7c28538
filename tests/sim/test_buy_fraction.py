"""The market's buy-fraction rule, by hand: f counts every voter ("all", the paper's) or only
the buyers and holders ("staying"), and the next round's demand, hence the price, follows."""

from __future__ import annotations

import numpy as np
import pytest

from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from sim.market import AuctionRandom, Market, MarketBatch, MarketConfig, item_rows

ZERO_INPUTS = dict.fromkeys(
    ("price", "length", "weight", "gill", "st1", "st2", "st3", "buy_fraction"), 0.0
)
ZERO_SENSORS = {"PG": 0.0, "SZ": 0.0, "LSR": 0.0, "ST": 0.0}


def scripted(name: str, *, bias: dict[str, float], follower: bool = False) -> Manifest:
    """A noiseless patron (one copy, σ = 0). With constant ``bias`` (B, L, Q) it always casts
    the same vote. A ``follower`` buys only when the price is below 4.995 and f above 0.2:
    PG = tanh(1000·(p − 4.995))⁺, LSR = tanh(100·(f − 0.2))⁺, B = 10·LSR − 10·PG − 5,
    L = 0, Q = −10."""
    data = honest_manifest(np.random.default_rng(0), name).model_dump()
    data["augmentation"] = {"copies": 1, "noise_std": 0.0, "noiseless_inputs": []}
    for neuron in data["external_sensor"].values():
        neuron["weights"] = dict(ZERO_INPUTS)
        neuron["bias"] = 0.0
    for neuron, b in zip(data["decision"].values(), (bias["B"], bias["L"], bias["Q"]), strict=True):
        neuron["weights"] = dict(ZERO_SENSORS)
        neuron["bias"] = b
    if follower:
        sensor = data["external_sensor"]
        sensor["PG"]["weights"]["price"] = 1.0
        sensor["PG"]["bias"] = -4.995
        sensor["PG"]["activation"] = {
            "kind": "threshold",
            "a": 1000.0,
            "c": 0.0,
            "negative_slope": 0.0,
        }
        sensor["LSR"]["weights"]["buy_fraction"] = 1.0
        sensor["LSR"]["activation"] = {
            "kind": "threshold",
            "a": 100.0,
            "c": 0.2,
            "negative_slope": 0.0,
        }
        data["decision"]["B"]["weights"].update(LSR=10.0, PG=-10.0)
    return Manifest.model_validate(data)


BUYER = {"B": 10.0, "L": 0.0, "Q": 0.0}
HOLDER = {"B": 0.0, "L": 10.0, "Q": 0.0}
QUITTER = {"B": 0.0, "L": 0.0, "Q": 10.0}
FOLLOWER = {"B": -5.0, "L": 0.0, "Q": -10.0}


def crowd() -> list[Manifest]:
    """One buyer, one holder, two quitters, two followers (positions 0..5)."""
    return [
        scripted("buyer", bias=BUYER),
        scripted("holder", bias=HOLDER),
        scripted("quitter-1", bias=QUITTER),
        scripted("quitter-2", bias=QUITTER),
        scripted("follower-1", bias=FOLLOWER, follower=True),
        scripted("follower-2", bias=FOLLOWER, follower=True),
    ]


def config(rule: str) -> MarketConfig:
    return MarketConfig(n_fish=2, n_rows=1, seed=4, buy_fraction=rule)


def test_round_0_is_the_same_under_both_rules():
    # f starts at ½: the followers see a price of 5.00 ≥ 4.995 and hold. One buy ≤ 2 fish:
    # low demand, the buyer pays 5.00, the price falls by 0.01 and the quitters leave.
    for rule in ("all", "staying"):
        first = Market(crowd(), config(rule)).step()
        assert first.votes == {"buy": 1, "hold": 3, "quit": 2}
        assert first.buyers == [(0, 5.0)] and first.quitters == [2, 3]
        assert first.next_price == pytest.approx(4.99) and first.n_available_after == 1


def test_all_counts_the_quitters_so_f_is_one_sixth_and_the_price_walks_down():
    # f = 1 buy / 6 voters = 0.167 < 0.2: at 4.99 the followers still hold, no one buys, the
    # price falls 0.01 a round until it drops below the threshold 4.80: 21 rounds in all.
    records = list(Market(crowd(), config("all")).run())
    second = records[1]
    assert second.votes == {"buy": 0, "hold": 3, "quit": 0}
    assert second.price == pytest.approx(4.99) and second.next_price == pytest.approx(4.98)
    assert len(records) == 21 and records[-1].stop_reason == "stalemate"
    assert [round(r.price, 5) for r in records] == [round(5.0 - 0.01 * i, 5) for i in range(21)]
    assert [b for r in records for b in r.buyers] == [(0, 5.0)]


def test_staying_ignores_the_quitters_so_f_is_one_quarter_and_demand_raises_the_price():
    # f = 1 buy / (1 buy + 3 holds) = 0.25 > 0.2: at 4.99 both followers buy; 2 buys > 1 fish
    # is high demand: nobody buys, the threshold becomes 4.99 + 0.01 and the price rises by
    # 0.05 − u·0.01, u the auction's next uniform draw on [0, 4).
    market = Market(crowd(), config("staying"))
    market.step()
    second = market.step()
    assert second.votes == {"buy": 2, "hold": 1, "quit": 0}
    assert second.buyers == [] and second.n_available_after == 1
    random = AuctionRandom.from_seed(4)
    item_rows(config("staying"), random.numpy)  # the draws the rows made
    u = random.numpy.uniform(0, 4)
    assert second.next_price == round(4.99 + 0.05 - u * 0.01, 5)  # recorded to 5 decimals
    assert market._engine.threshold[0] == pytest.approx(5.0)
    # f = 2 / 3 now, but at a price ≥ 4.995 the followers hold again.
    third = market.step()
    assert third.votes == {"buy": 0, "hold": 3, "quit": 0}


def test_staying_with_nobody_staying_on_a_row_gives_f_zero():
    # Everyone quits: no buyer and no holder, f = 0/0 taken as 0 (the run then ends).
    quitters = [scripted(f"q{i}", bias=QUITTER) for i in range(3)]
    engine = MarketBatch([(quitters, config("staying")), (quitters, config("all"))])
    records = engine.step()
    assert [r.stop_reason for r in records if r is not None] == ["no_patrons", "no_patrons"]
    assert engine.rows[:, 0, 7].tolist() == [0.0, 0.0]


def test_rules_mix_in_one_batch_as_alone():
    together = MarketBatch([(crowd(), config("all")), (crowd(), config("staying"))])
    first, second = together.step(), together.step()
    assert [r.votes["buy"] for r in second if r is not None] == [0, 2]
    assert first[0] == first[1]


def test_an_unknown_rule_is_refused_by_name():
    with pytest.raises(ValueError, match="buy_fraction must be one of"):
        MarketConfig(n_fish=1, buy_fraction="buyers")  # type: ignore[arg-type]
