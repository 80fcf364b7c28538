"""The auction studies: tiny-budget runs, determinism, the same auctions across settings,
screening that leaves exactly the honest auction."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

import screener
from sim.market import Market
from studies.auctions import (
    ComparisonConfig,
    Setting,
    StudyConfig,
    plan_auction,
    run_auctions,
    run_comparison,
    run_study,
    study_settings,
)

TINY = {"rarities": (0.2, 0.8), "trials": 2, "patrons": 16, "seed": 3}


def without_time(result: dict) -> dict:
    return {k: v for k, v in result.items() if k != "elapsed_s"}


def test_tiny_study_writes_its_artifacts_and_consistent_numbers(tmp_path):
    result = run_study(StudyConfig(**TINY), out_dir=tmp_path)
    assert result["auctions"] == 4 and len(result["rows"]) == 2
    for name in ("results.csv", "summary.json", "price_vs_supply.png", "purchase_rate.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    with (tmp_path / "results.csv").open() as handle:
        lines = list(csv.DictReader(handle))
    assert len(lines) == 4
    for row in result["rows"]:
        mine = [line for line in lines if float(line["rarity"]) == row["rarity"]]
        assert row["n_fish"] == int(row["rarity"] * 16) and row["trials"] == 2
        sold = [int(line["sold"]) for line in mine]
        assert row["purchase_rate"] == pytest.approx(np.mean([s / row["n_fish"] for s in sold]))
        assert row["buyer_fraction"] == pytest.approx(np.mean([s / 16 for s in sold]))
        revenue = [float(line["revenue"]) for line in mine]
        assert row["revenue"] == pytest.approx(np.mean(revenue), abs=1e-5)
        if sum(sold):
            assert row["mean_price"] == pytest.approx(sum(revenue) / sum(sold), abs=1e-5)
            assert 4.7 < row["mean_price"] < 5.6
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["config"]["trials"] == 2 and summary["rows"] == result["rows"]


def test_same_seed_same_study(tmp_path):
    config = StudyConfig(**{**TINY, "fine_tune": True})
    first = run_study(config, out_dir=tmp_path / "a")
    again = run_study(config, out_dir=tmp_path / "b")
    assert without_time(first) == without_time(again)
    other = run_study(StudyConfig(**{**TINY, "seed": 4}), out_dir=tmp_path / "c")
    assert other["rows"] != first["rows"]


def test_grid_runs_four_settings_on_the_same_auctions():
    settings = study_settings(StudyConfig(grid=True, saboteurs=0.25))
    assert [(s.fine_tune, s.saboteurs) for s in settings] == [
        (False, 0.0),
        (True, 0.0),
        (False, 0.25),
        (True, 0.25),
    ]
    plans = [
        plan_auction(s, 0.5, 1, n_patrons=16, seed=7, max_iterations=64, fine_tune_rounds=4)
        for s in settings
    ]
    assert len({p.market.seed for p in plans}) == 1  # one market stream per (seed, rarity, trial)
    honest_plain, honest_tuned, sab_plain, _ = plans
    assert [m.external_sensor for m in honest_plain.patrons] == [
        m.external_sensor for m in honest_tuned.patrons
    ]
    assert sab_plain.patrons[:12] == honest_plain.patrons[:12]  # honest first, saboteurs last
    assert all(m.participant.startswith("saboteur") for m in sab_plain.patrons[12:])
    assert {p.n_fish for p in plans} == {8}


@pytest.mark.parametrize(
    ("n_patrons", "share", "saboteurs"),
    [(64, 0.5, 32), (63, 0.5, 32), (7, 0.5, 4), (10, 0.9, 9), (10, 0.25, 3), (16, 1.0, 16)],
)
def test_saboteurs_are_the_patrons_after_the_honest_share(n_patrons, share, saboteurs):
    """The reference's split: the first int((1 - share) · n) patrons honest, the rest saboteurs
    (its first int(n/2) honest at a half, so 32 of 63 are saboteurs)."""
    plan = plan_auction(
        Setting("compromised", False, share, False),
        0.5,
        0,
        n_patrons=n_patrons,
        seed=3,
        max_iterations=64,
        fine_tune_rounds=4,
    )
    names = [m.participant for m in plan.patrons]
    assert len(names) == n_patrons
    assert sum(name.startswith("saboteur") for name in names) == saboteurs
    assert all(name.startswith("honest") for name in names[: n_patrons - saboteurs])


def refuse_saboteurs(manifests):
    return [screener.Verdict(accepted=not m.participant.startswith("saboteur")) for m in manifests]


@pytest.mark.parametrize("fine_tune", [False, True])
def test_screening_out_the_saboteurs_leaves_the_honest_auction(monkeypatch, fine_tune):
    monkeypatch.setattr(screener, "screen_many", refuse_saboteurs)
    screened = Setting("screened", fine_tune, 0.5, True)
    plan = plan_auction(
        screened, 0.3, 0, n_patrons=20, seed=5, max_iterations=64, fine_tune_rounds=4
    )
    from studies.auctions import screen_auctions

    screen_auctions([plan])
    assert plan.refused == 10 and len(plan.patrons) == 10
    run_auctions([plan])
    honest = plan_auction(
        Setting("honest", fine_tune, 0.0, False),
        0.3,
        0,
        n_patrons=20,
        seed=5,
        max_iterations=64,
        fine_tune_rounds=4,
    )
    alone = list(Market(honest.patrons[:10], plan.market).run())
    assert plan.purchases == [price for r in alone for _, price in r.buyers]
    assert plan.iterations == len(alone) and plan.stop_reason == alone[-1].stop_reason


def test_the_real_screener_refuses_exactly_the_saboteurs(tmp_path):
    result = run_study(
        StudyConfig(rarities=(0.5,), trials=1, patrons=16, saboteurs=0.5, screen=True),
        out_dir=tmp_path,
    )
    assert result["refused"] == 8
    assert result["rows"][0]["refused"] == 8


def test_comparison_holds_one_table_per_configuration(tmp_path):
    config = ComparisonConfig(rarities=(0.3, 0.7), trials=1, patrons=16, seed=2)
    result = run_comparison(config, out_dir=tmp_path)
    configs = result["configurations"]
    names = ["honest", "honest+screened", "compromised", "compromised+screened", "honest-alone"]
    assert list(configs) == names
    assert result["auctions"] == 10 and result["buy_fraction"] == "all"
    for name, block in configs.items():
        assert [r["rarity"] for r in block["rows"]] == [0.3, 0.7], name
    assert result["rows"] == [r for name in names for r in configs[name]["rows"]]
    assert configs["honest"]["refused"] == 0 and configs["compromised"]["refused"] == 0
    assert configs["honest+screened"]["refused"] == 0  # the screener admits every honest one
    assert configs["honest+screened"]["rows"] == [
        {**row, "setting": "honest+screened", "screen": True} for row in configs["honest"]["rows"]
    ]
    assert configs["compromised+screened"]["refused"] == 16  # 8 saboteurs × 2 auctions
    assert configs["honest-alone"]["refused"] == 0
    for name in ("results.csv", "comparison.csv", "comparison.png", "summary.json"):
        assert (tmp_path / name).stat().st_size > 0
    # Saboteurs drag the price to the base price once supply is ample.
    high = configs["compromised"]["rows"][1]
    assert high["mean_price"] is None or high["mean_price"] <= 5.0 + 1e-9
    lines = result["caption"].splitlines()
    assert [line.split(":")[0] for line in lines] == names
    assert "8 honest patrons" in lines[4] and "last 8 of the 16" in lines[2]


def differing(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in ("setting", "refused", "saboteurs", "screen")}


def test_honest_alone_is_the_compromised_population_without_its_saboteurs(tmp_path):
    # The screener refuses exactly the saboteurs and nothing fine-tunes, so the screened
    # auctions are the honest-alone ones: the same fish, seeds and honest patrons.
    config = ComparisonConfig(rarities=(0.2, 0.6), trials=2, patrons=16, seed=5)
    configs = run_comparison(config, out_dir=tmp_path)["configurations"]
    alone, screened = configs["honest-alone"], configs["compromised+screened"]
    assert [differing(r) for r in alone["rows"]] == [differing(r) for r in screened["rows"]]
    with (tmp_path / "results.csv").open() as handle:
        lines = [line for line in csv.DictReader(handle) if line["setting"] == "honest-alone"]
    assert len(lines) == 4
    assert all(line["n_patrons"] == "16" and line["admitted"] == "8" for line in lines)
    assert {line["n_fish"] for line in lines} == {"3", "9"}  # the whole population's fish
    honest = configs["honest"]["rows"]
    assert [r["n_fish"] for r in honest] == [r["n_fish"] for r in alone["rows"]]


def test_the_buy_fraction_rule_reaches_every_auction(tmp_path):
    plan = plan_auction(
        Setting("honest", False, 0.0, False),
        0.5,
        0,
        n_patrons=8,
        seed=1,
        max_iterations=64,
        fine_tune_rounds=4,
        buy_fraction="staying",
    )
    assert plan.market.buy_fraction == "staying"
    base = {"rarities": (0.1, 0.3, 0.5), "trials": 2, "patrons": 32, "seed": 1}
    rows = {
        rule: run_comparison(ComparisonConfig(**base, buy_fraction=rule), out_dir=tmp_path / rule)
        for rule in ("all", "staying")
    }
    assert rows["staying"]["buy_fraction"] == "staying"
    assert rows["all"]["rows"] != rows["staying"]["rows"]


def test_freeze_pfc_leaves_every_patrons_judge_untrained(tmp_path):
    def plan(freeze_pfc: bool):
        return plan_auction(
            Setting("compromised", True, 0.5, False),
            0.5,
            0,
            n_patrons=8,
            seed=1,
            max_iterations=64,
            fine_tune_rounds=4,
            freeze_pfc=freeze_pfc,
        )

    trained, frozen = plan(False), plan(True)
    assert all(p.pfc.trainable for p in trained.patrons)
    assert not any(p.pfc.trainable for p in frozen.patrons)
    unfrozen = [
        p.model_copy(update={"pfc": q.pfc})
        for p, q in zip(frozen.patrons, trained.patrons, strict=True)
    ]
    assert unfrozen == trained.patrons  # nothing else differs
    result = run_study(StudyConfig(**TINY, fine_tune=True, freeze_pfc=True), out_dir=tmp_path)
    assert result["auctions"] == 4 and result["settings"] == ["honest+fine-tune"]
