"""The auction engine: price rules, stop conditions, batched == per-patron loop, checkpoints."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from agents.manifest import Manifest
from agents.negotiator import honest_manifest, saboteur_manifest
from sim.market import (
    IterationRecord,
    Market,
    MarketBatch,
    MarketConfig,
)
from tests.support.loops import loop_auction


def patrons(seed: int, n_honest: int, n_saboteurs: int = 0, lr: float | None = None):
    rng = np.random.default_rng(seed)
    out = [honest_manifest(rng, f"h{i}") for i in range(n_honest)]
    out += [saboteur_manifest(rng, f"s{i}") for i in range(n_saboteurs)]
    if lr is None:
        return out
    # Strong learning rates so that fine-tuning visibly changes decisions.
    return [
        m.model_copy(update={"fine_tuning": m.fine_tuning.model_copy(update={"learning_rate": lr})})
        for m in out
    ]


CASES = [
    # seed, honest, saboteurs, fish, fine-tune, all rows, buy fraction
    (0, 12, 0, 2, False, True, "all"),
    (1, 12, 0, 6, True, True, "all"),
    (2, 8, 8, 5, True, False, "all"),
    (3, 12, 4, 10, False, False, "all"),
    (4, 16, 0, 1, True, True, "all"),
    (5, 12, 4, 6, True, True, "staying"),
    (6, 10, 6, 3, False, False, "staying"),
]


@pytest.mark.parametrize(("seed", "n_honest", "n_sab", "fish", "tune", "all_rows", "rule"), CASES)
def test_batched_market_equals_the_per_patron_loop(
    seed, n_honest, n_sab, fish, tune, all_rows, rule
):
    manifests = patrons(seed, n_honest, n_sab, lr=0.5)
    config = MarketConfig(
        n_fish=fish,
        n_rows=24,
        fine_tune=tune,
        seed=seed,
        evaluate_all_rows=all_rows,
        buy_fraction=rule,
    )
    expected = loop_auction(manifests, config)
    got = list(Market(manifests, config).run())
    assert got == expected
    assert len(got) >= 2
    assert any(r.fine_tuned for r in got) == tune


def test_fine_tuning_changes_the_auction_and_the_patrons():
    manifests = patrons(1, 12, 0, lr=0.5)
    tuned = Market(manifests, MarketConfig(n_fish=6, n_rows=24, fine_tune=True, seed=1))
    plain = Market(manifests, MarketConfig(n_fish=6, n_rows=24, fine_tune=False, seed=1))
    a, b = list(tuned.run()), list(plain.run())
    assert any(r.fine_tuned for r in a) and not any(r.fine_tuned for r in b)
    assert [(r.votes, r.row_votes) for r in a] != [(r.votes, r.row_votes) for r in b]
    changed = [m for m, o in zip(tuned.current_manifests(), manifests, strict=True) if m != o]
    assert changed and all(m.fine_tuning.epochs > 0 for m in changed)
    assert plain.current_manifests() == manifests


def test_fine_tuning_runs_in_the_first_four_iterations_by_default():
    """The paper's schedule (the reference's bug: five), on 64 honest patrons of the paper."""
    rng = np.random.default_rng(3)
    manifests = [honest_manifest(rng, "honest") for _ in range(64)]
    for rounds, expected in ((None, [0, 1, 2, 3]), (5, [0, 1, 2, 3, 4])):
        options = {} if rounds is None else {"fine_tune_rounds": rounds}
        config = MarketConfig(n_fish=6, fine_tune=True, seed=0, **options)
        records = list(Market(manifests, config).run())
        assert len(records) > len(expected)  # the auction outlived its fine-tuning
        assert [r.iteration for r in records if r.fine_tuned] == expected


def test_saboteurs_alone_walk_the_price_down_to_the_stalemate():
    records = list(Market(patrons(0, 0, 6), MarketConfig(n_fish=3, n_rows=8)).run())
    assert len(records) == 21  # 5.00, 4.99, ..., 4.80; then 4.79 < 4.8
    assert [round(r.price, 5) for r in records[:3]] == [5.0, 4.99, 4.98]
    assert all(r.votes == {"buy": 0, "hold": 6, "quit": 0} for r in records)
    assert all(r.row_votes == {"buy": 0, "hold": 48, "quit": 0} for r in records)
    assert records[-1].stop_reason == "stalemate" and records[-1].next_price < 4.8
    assert not any(r.buyers for r in records) and records[-1].n_available_after == 3


def test_high_demand_raises_price_and_threshold():
    market = Market(patrons(5, 20), MarketConfig(n_fish=1, n_rows=8, seed=5))
    first = market.step()
    assert first.votes["buy"] > 1 and not first.buyers
    assert 5.0 + 0.01 < first.next_price <= 5.05
    assert market._engine.threshold[0] == pytest.approx(5.01)
    records = [first, *market.run()]
    for before, after in itertools.pairwise(records):
        assert after.price == before.next_price
        assert after.n_available == before.n_available_after
    raises = [r for r in records if r.votes["buy"] > r.n_available]
    assert all(0.01 < r.next_price - r.price <= 0.05 + 1e-12 for r in raises)
    sales = [r for r in records if r.buyers]
    assert all(b[1] == r.price for r in sales for b in r.buyers)


def test_low_demand_sells_to_every_buyer_at_the_current_price():
    manifests = patrons(6, 10)
    record = Market(manifests, MarketConfig(n_fish=10, n_rows=8)).step()
    assert record.votes["buy"] == len(record.buyers) > 0
    assert all(price == 5.0 for _, price in record.buyers)
    assert record.next_price == pytest.approx(4.99)
    assert record.n_available_after == 10 - len(record.buyers)


def test_sold_out_no_patrons_and_max_iterations():
    sold = list(Market(patrons(7, 10), MarketConfig(n_fish=1, n_rows=8, seed=2)).run())
    assert sold[-1].stop_reason in {"sold_out", "no_patrons", "stalemate"}
    everyone_buys = list(Market(patrons(8, 5), MarketConfig(n_fish=5, n_rows=8)).run())
    assert everyone_buys[-1].stop_reason in {"sold_out", "no_patrons"}
    capped = list(Market(patrons(0, 0, 3), MarketConfig(n_fish=2, max_iterations=3)).run())
    assert len(capped) == 3 and capped[-1].stop_reason == "max_iterations"
    assert [r.finished for r in capped] == [False, False, True]


def test_market_refuses_to_step_after_the_end_and_bad_configs():
    market = Market(patrons(0, 0, 2), MarketConfig(n_fish=1, max_iterations=1))
    market.step()
    assert market.finished and market.iteration == 1
    with pytest.raises(RuntimeError):
        market.step()
    with pytest.raises(ValueError, match="increment"):
        MarketConfig(n_fish=1, increment=0.01, decrement=0.01)
    with pytest.raises(ValueError, match="n_fish"):
        MarketConfig(n_fish=-1)


def test_same_seed_same_auction_and_batch_equals_alone():
    configs = [
        (patrons(10, 12, 4, lr=0.3), MarketConfig(n_fish=3, n_rows=16, fine_tune=True, seed=10)),
        (patrons(11, 9), MarketConfig(n_fish=7, n_rows=16, seed=11, evaluate_all_rows=False)),
        (patrons(12, 14, lr=0.3), MarketConfig(n_fish=1, n_rows=16, fine_tune=True, seed=12)),
        # the first one's seed again (the batch starts it from a copy of the first's start)
        (patrons(13, 10), MarketConfig(n_fish=2, n_rows=16, fine_tune=True, seed=10)),
    ]
    alone = [list(Market(m, c).run()) for m, c in configs]
    assert alone[0] == list(Market(*configs[0]).run())
    engine = MarketBatch(configs)
    together: list[list[IterationRecord]] = [[] for _ in configs]
    while not engine.finished.all():
        for a, record in enumerate(engine.step()):
            if record is not None:
                together[a].append(record)
    assert together == alone
    other_seed = MarketConfig(n_fish=3, n_rows=16, fine_tune=True, seed=99)
    assert list(Market(configs[0][0], other_seed).run()) != alone[0]


@pytest.mark.parametrize("tune", [False, True])
def test_checkpoint_restore_continues_bit_identically(tune):
    manifests = patrons(20, 14, 4, lr=0.3)
    config = MarketConfig(n_fish=4, n_rows=16, fine_tune=tune, seed=20)
    full = list(Market(manifests, config).run())
    assert len(full) >= 4
    for k in (1, 2, len(full) - 1):
        market = Market(manifests, config)
        head = [market.step() for _ in range(k)]
        blob = market.checkpoint()
        market.step()  # the original goes on; the restored copy must not care
        restored = Market.restore(manifests, config, blob)
        assert restored.iteration == k
        assert head + list(restored.run()) == full
        assert restored.current_manifests() == market.current_manifests() or k < len(full) - 1
    with pytest.raises(ValueError, match="manifests"):
        Market.restore(manifests[:-1], config, blob)


def test_rescreening_reverts_refused_fine_tuning():
    manifests = patrons(30, 10, lr=0.5)
    config = MarketConfig(n_fish=2, n_rows=16, fine_tune=True, seed=30)
    asked: list[int] = []

    def rescreen(index: int, manifest: Manifest) -> bool:
        asked.append(index)
        assert manifest.participant == manifests[index].participant
        return index % 2 == 0

    market = Market(manifests, config, rescreen=rescreen)
    records = list(market.run())
    assert asked and all(manifests[i].fine_tuning.epochs > 0 for i in asked)
    reverted = {i for r in records for i in r.reverted}
    kept = {i for r in records for i in r.fine_tuned}
    assert reverted and all(i % 2 == 1 for i in reverted) and all(i % 2 == 0 for i in kept)
    now = market.current_manifests()
    assert all(now[i] == manifests[i] for i in reverted)
    assert any(now[i] != manifests[i] for i in kept)


def test_records_serialise():
    record = Market(patrons(0, 5), MarketConfig(n_fish=2, n_rows=8)).step()
    data = record.to_dict()
    assert data["votes"] == record.votes and data["price"] == 5.0
    assert all(set(b) == {"patron", "price"} for b in data["buyers"])
