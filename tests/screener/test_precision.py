"""The screener computes as the market does (float64): a model whose B and L tie in float32 on
every row the auction reaches, while L wins in float64 by less than 1e-8, holds in every
auction. A float32 screener saw it buy at every price and admitted it (an outside review's
find; both variants are in the red team's corpus)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from agents.batch import from_manifests
from agents.forward import clean_logits
from agents.negotiator import honest_manifest
from screener import screen
from sim.market import MarketBatch, MarketConfig
from tests.support.corpus import red_team_corpus

HOLD = 1
TIES = {e.construction: e.manifest for e in red_team_corpus() if "float32-tie" in e.construction}


@pytest.mark.parametrize("name", sorted(TIES))
def test_a_model_that_holds_only_in_float64_is_judged_as_the_market_sees_it(name: str) -> None:
    model = TIES[name]
    rows = torch.tensor([[p, 1, 1, 1, 0.5, 0.5, 0.5, 0.0] for p in (4.8, 5.0, 6.0, 12.5)])
    for dtype, expected in ((torch.float32, 0), (torch.float64, HOLD)):  # the attack's premise
        choices = clean_logits(from_manifests([model], dtype), rows).argmax(dim=-1)
        assert choices.flatten().tolist() == [expected] * 4, dtype
    # in a real auction (the market's arithmetic) it holds at every iteration it votes in
    rng = np.random.default_rng(3)
    honest = [honest_manifest(rng, f"h{i}") for i in range(5)]
    config = MarketConfig(n_fish=2, seed=11, fine_tune=False)
    market = MarketBatch([([*honest, model], config)], explain=True)
    votes = []
    while not market.finished.all():
        (record,) = market.step()
        assert record is not None
        votes += [e.vote for e in record.explanations if e.patron == len(honest)]
    assert votes and set(votes) == {"hold"}, votes

    verdict = screen(model)
    assert not verdict.accepted
    held = [r.message for r in verdict.reasons if r.rule == "sincere-hold"]
    assert held, verdict.reasons
    assert "L leading B by" in held[0]  # the scores print alike: the margin is named
