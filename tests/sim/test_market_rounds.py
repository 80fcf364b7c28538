"""Fine-tuning rounds: per-patron seeds, remote rounds (pending → apply_round), and the
records of auctions without fine-tuning, which must not move."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.batch import from_manifests, to_manifest
from agents.fine_tuning import fine_tune_round
from agents.manifest import Manifest
from agents.negotiator import honest_manifest, saboteur_manifest
from sim.market import (
    FineTuneRound,
    Market,
    MarketBatch,
    MarketConfig,
    round_seeds,
    round_update_problems,
)

EXPECTED = Path(__file__).with_name("expected") / "no_fine_tune_records.json"
"""Records of auctions without fine-tuning, computed before fine-tuning got per-patron seeds."""


def patrons(seed: int, n_honest: int, n_saboteurs: int = 0) -> list[Manifest]:
    rng = np.random.default_rng(seed)
    out = [honest_manifest(rng, f"h{i}") for i in range(n_honest)]
    return out + [saboteur_manifest(rng, f"s{i}") for i in range(n_saboteurs)]


def strong(manifests: list[Manifest], lr: float = 0.3) -> list[Manifest]:
    """Learning rates that visibly move the patrons."""
    return [
        m.model_copy(update={"fine_tuning": m.fine_tuning.model_copy(update={"learning_rate": lr})})
        for m in manifests
    ]


def varied(manifests: list[Manifest], seed: int) -> list[Manifest]:
    """Every patron its own batch size (1-64), copies (1-16), noise, epochs (1-4) and
    learning rate (up to 1e-3): shapes the server's bands pad differently from a patron alone,
    and steps that amplify any last-bit difference (rounds later, 1e-17 had become 1e-2)."""
    rng = np.random.default_rng(seed)
    return [
        m.model_copy(
            update={
                "augmentation": m.augmentation.model_copy(
                    update={"copies": int(rng.integers(1, 17)), "noise_std": 0.05}
                ),
                "fine_tuning": m.fine_tuning.model_copy(
                    update={
                        "epochs": int(rng.integers(1, 5)),
                        "batch_size": int(rng.integers(1, 65)),
                        "learning_rate": float(rng.uniform(1e-4, 1e-3)),
                    }
                ),
            }
        )
        for m in manifests
    ]


def faithful(manifest: Manifest, round_: FineTuneRound, position: int) -> Manifest:
    """What a faithful remote agent uploads: its own model fine-tuned alone on the round."""
    mine = from_manifests([manifest])
    tuned = fine_tune_round(
        mine,
        torch.tensor(round_.rows),
        np.array([round_.fine_tune_seed], dtype=np.uint64),
        np.array([round_.augmentation_seed], dtype=np.uint64),
        np.array([position]),
    )
    return to_manifest(tuned, 0)


def test_auctions_without_fine_tuning_keep_their_records():
    stored = json.loads(EXPECTED.read_text())["auctions"]
    work = []
    for case in stored:
        manifests = patrons(case["seed"], case["honest"], case["saboteurs"])
        config = MarketConfig(
            n_fish=case["n_fish"], seed=case["seed"], evaluate_all_rows=case["evaluate_all_rows"]
        )
        assert [r.to_dict() for r in Market(manifests, config).run()] == case["records"]
        work.append((manifests, config))
    # Next to a fine-tuned auction in one lock-step batch, too.
    work.insert(1, (strong(patrons(14, 16)), MarketConfig(n_fish=5, seed=14, fine_tune=True)))
    engine = MarketBatch(work)
    records: list[list[dict]] = [[] for _ in work]
    while not engine.finished.all():
        for mine, record in zip(records, engine.step(), strict=True):
            if record is not None:
                mine.append(record.to_dict())
    assert [records[i] for i in (0, 2, 3)] == [case["records"] for case in stored]
    assert any(r["fine_tuned"] for r in records[1])


def test_round_seeds_differ_by_auction_and_iteration():
    seeds = {round_seeds(s, i) for s in range(4) for i in range(4)}
    assert len(seeds) == 16 and all(a != b for a, b in seeds)
    assert all(0 <= a < 2**53 and 0 <= b < 2**53 for a, b in seeds)
    assert round_seeds(3, 2) == round_seeds(3, 2)


def play_remote(
    manifests: list[Manifest], config: MarketConfig, skip: set[int] = frozenset()
) -> tuple[list, list[Manifest]]:
    """A remote auction where every asked patron (but ``skip``) answers faithfully."""
    return finish(Market(manifests, config), skip)


def finish(market: Market, skip: set[int] = frozenset()) -> tuple[list, list[Manifest]]:
    """Play a remote market to its end, every asked patron (but ``skip``) faithful."""
    records = []
    while not market.finished:
        records.append(market.step())
        pending = market.pending_round
        if pending is not None:
            with pytest.raises(RuntimeError, match="fine-tuning round"):
                market.step()
            now = market.current_manifests()
            market.apply_round(
                {p: faithful(now[p], pending, p) for p in pending.patrons if p not in skip}
            )
    return records, market.current_manifests()


def assert_identical(a: list[Manifest], b: list[Manifest]) -> None:
    """Two patron lists with the same parameters, bit for bit."""
    left, right = from_manifests(a).parameters(), from_manifests(b).parameters()
    assert all(torch.equal(left[k], right[k]) for k in left)


@pytest.mark.parametrize(
    ("seed", "n_honest", "n_sab", "fish", "rows", "settings"),
    [(1, 12, 0, 3, 24, "strong"), (2, 10, 4, 2, 24, "strong"), (53, 24, 0, 5, 64, "varied")],
)
def test_faithful_remote_rounds_replay_the_server_auction(
    seed, n_honest, n_sab, fish, rows, settings
):
    """Each patron's fine-tuning is its own, bit for bit, whoever shares the server's batch."""
    plain = patrons(seed, n_honest, n_sab)
    manifests = strong(plain) if settings == "strong" else varied(plain, seed)
    server = MarketConfig(n_fish=fish, n_rows=rows, fine_tune=True, seed=seed, fine_tune_rounds=8)
    remote = MarketConfig(
        n_fish=fish, n_rows=rows, fine_tune=True, seed=seed, fine_tune_rounds=8,
        fine_tune_mode="remote",
    )  # fmt: skip
    market = Market(manifests, server)
    expected = list(market.run())
    got, final = play_remote(manifests, remote)
    assert [dataclass_without_tuning(r) for r in got] == [
        dataclass_without_tuning(r) for r in expected
    ]
    assert any(r.fine_tuned for r in expected)
    assert_identical(final, market.current_manifests())
    assert final != manifests  # the patrons moved


def dataclass_without_tuning(record) -> dict:
    """A record but who fine-tuned (the server mode reports it, the remote one cannot)."""
    out = record.to_dict()
    del out["fine_tuned"], out["reverted"]
    return out


def test_silent_patrons_keep_their_weights_and_the_auction_goes_on():
    manifests = strong(patrons(3, 10))
    config = MarketConfig(n_fish=2, n_rows=16, fine_tune=True, seed=3, fine_tune_mode="remote")
    _, final = play_remote(manifests, config, skip={0, 1})
    assert final[0] == manifests[0] and final[1] == manifests[1]
    moved = [p for p in range(2, 10) if manifests[p].fine_tuning.epochs > 0]
    assert moved and all(final[p] != manifests[p] for p in moved)


def test_a_pending_round_survives_checkpoint_and_restore():
    manifests = strong(patrons(4, 10))
    config = MarketConfig(n_fish=2, n_rows=16, fine_tune=True, seed=4, fine_tune_mode="remote")
    market = Market(manifests, config)
    market.step()
    pending = market.pending_round
    assert pending is not None and pending.iteration == 0
    restored = Market.restore(manifests, config, market.checkpoint())
    again = restored.pending_round
    assert again is not None
    assert np.array_equal(again.rows, pending.rows) and again.patrons == pending.patrons
    assert (again.fine_tune_seed, again.augmentation_seed) == (
        pending.fine_tune_seed,
        pending.augmentation_seed,
    )
    updates = {p: faithful(manifests[p], pending, p) for p in pending.patrons}
    market.apply_round(updates)
    restored.apply_round(updates)
    assert finish(restored) == finish(market)


def test_apply_round_refuses_strangers_and_design_changes():
    manifests = strong(patrons(5, 8))
    config = MarketConfig(n_fish=1, n_rows=16, fine_tune=True, seed=5, fine_tune_mode="remote")
    market = Market(manifests, config)
    with pytest.raises(ValueError, match="no pending"):
        market.apply_round({})
    record = market.step()
    pending = market.pending_round
    assert pending is not None
    gone = set(record.quitters) | {p for p, _ in record.buyers}
    assert sorted(set(range(8)) - gone) == pending.patrons
    if gone:
        with pytest.raises(ValueError, match="not asked"):
            market.apply_round({min(gone): manifests[min(gone)]})
    p = pending.patrons[0]
    data = faithful(manifests[p], pending, p).model_dump(mode="json")
    data["augmentation"]["copies"] = 3
    data["external_sensor"]["PG"]["activation"]["a"] = 7.0
    changed = Manifest.model_validate(data)
    problems = round_update_problems(manifests[p], changed)
    assert [path for path, _ in problems] == [
        "augmentation.copies",
        "external_sensor.PG.activation.a",
    ]
    with pytest.raises(ValueError, match=r"augmentation\.copies"):
        market.apply_round({p: changed})
    assert market.pending_round is not None  # nothing applied
    renamed = manifests[p].model_copy(update={"participant": "someone-else"})
    assert [path for path, _ in round_update_problems(manifests[p], renamed)] == ["participant"]
    assert round_update_problems(manifests[p], faithful(manifests[p], pending, p)) == []
    market.apply_round({})
    assert market.pending_round is None and market.current_manifests() == manifests


def _leaves(data: object, path: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    if isinstance(data, dict):
        return [leaf for key, value in data.items() for leaf in _leaves(value, (*path, key))]
    return [path]


def _nudged(value: object) -> object:
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    if isinstance(value, float):
        return value * 0.5 + 0.01
    return f"{value}x"


def test_the_design_is_everything_but_the_weights_and_biases():
    """``design`` (one pydantic dump, weights and biases excluded) tells two manifests apart
    exactly when ``design_changes`` (the walk that names what differs) finds something: for
    every field of the manifest changed alone."""
    from sim.market.design import design, design_changes

    base = honest_manifest(np.random.default_rng(3), "designed")
    data = base.model_dump(mode="json")
    moved, kept = 0, 0
    for path in _leaves(data):
        changed = json.loads(json.dumps(data))
        node = changed
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = _nudged(node[path[-1]])
        try:
            other = Manifest.model_validate(changed)
        except ValueError:
            continue  # the nudge left the field's range: not a manifest
        named = design_changes(data, other.model_dump(mode="json"))
        numbers = "weights" in path or path[-1] == "bias"
        assert (design(other) == design(base)) == (named == []) == numbers, path
        assert round_update_problems(base, other) == named
        moved, kept = moved + numbers, kept + (not numbers)
    assert moved == 83 and kept > 10  # every weight and bias, and the design fields
