"""Re-screening of fine-tuned patrons: one function (``screener.rescreen``) for the server's
auctions and for ``srd auction-study --screen``; a refused version is reverted."""

from __future__ import annotations

import numpy as np
import torch

import screener
import server.auctions.steps
from agents.batch import FSNBatch, from_manifests
from agents.negotiator import honest_manifest, saboteur_manifest
from sim.market import Market, MarketConfig
from studies.auctions import Setting, plan_auction, run_auctions


def test_the_server_rescreens_as_the_study_and_reverts_what_it_would_hold():
    """Margin 0 (the study's, which has no inspector): the study's re-screening. A margin: a
    version the server would hold for an inspector is reverted, as a held remote upload does
    not bid."""
    rng = np.random.default_rng(5)
    models = [honest_manifest(rng, f"h{i}") for i in range(8)]
    models.append(saboteur_manifest(rng, "s"))
    batch = from_manifests(models)
    verdicts = screener.rescreen_many(models)
    judged = list(server.auctions.steps.rescreening(0.0)(batch))
    kept = [j is True for j in judged]
    assert kept == screener.rescreen(batch).tolist() == [v.accepted for v in verdicts]
    # a version not kept carries the screener's reasons, as its auction stores them
    refused = [(j, v) for j, v in zip(judged, verdicts, strict=True) if j is not True]
    assert refused and all(j == [r.to_dict() for r in v.reasons] for j, v in refused)
    held = [screener.review(v, 1.0) == "accepted" for v in verdicts]
    strict = list(server.auctions.steps.rescreening(1.0)(batch))
    assert [j is True for j in strict] == held
    assert all(j for j in strict if j is not True)  # each held one says which bar held it
    assert held.count(True) < kept.count(True)  # the margin reverts some


def test_rescreen_keeps_what_the_screener_accepts():
    rng = np.random.default_rng(3)
    models = [honest_manifest(rng, f"h{i}") for i in range(8)]
    kept = screener.rescreen(from_manifests(models))
    assert kept.dtype == np.bool_ and kept.tolist() == [
        v.accepted for v in screener.rescreen_many(models)
    ]
    assert kept.all()


def fine_tuned_study_auction():
    setting = Setting("screened", True, 0.0, True)
    return plan_auction(setting, 0.2, 0, n_patrons=16, seed=3, max_iterations=64,
                        fine_tune_rounds=4)  # fmt: skip


def test_the_study_rescreens_every_fine_tuned_patron_after_each_round(monkeypatch):
    seen: list[list[str]] = []
    plan = fine_tuned_study_auction()
    moving = {m.participant for m in plan.patrons if m.fine_tuning.epochs > 0}
    refused = min(moving)

    def spy(patrons: FSNBatch) -> np.ndarray:
        seen.append(list(patrons.participants))
        return np.array([name != refused for name in patrons.participants])

    monkeypatch.setattr(screener, "rescreen", spy)
    run_auctions([plan])
    assert seen and all(set(names) <= moving for names in seen)
    assert refused in seen[0]
    assert plan.reverted == sum(refused in names for names in seen)
    assert plan.result_row()["reverted"] == plan.reverted


def test_a_refused_version_is_reverted_as_the_server_does():
    plan = fine_tuned_study_auction()
    refused = next(m.participant for m in plan.patrons if m.fine_tuning.epochs > 0)

    def refuse_one(patrons: FSNBatch) -> np.ndarray:
        return np.array([name != refused for name in patrons.participants])

    config = MarketConfig(n_fish=3, fine_tune=True, seed=5)
    market = Market(plan.patrons, config, rescreen_batch=refuse_one)
    records = list(market.run())
    index = [m.participant for m in plan.patrons].index(refused)
    assert records[0].reverted == [index]
    after = from_manifests(market.current_manifests())
    before = from_manifests(plan.patrons)
    assert torch.equal(after.fc_weight[index], before.fc_weight[index])
    moved = [i for i, m in enumerate(plan.patrons) if m.fine_tuning.epochs > 0 and i != index]
    assert not torch.equal(after.fc_weight[moved], before.fc_weight[moved])
