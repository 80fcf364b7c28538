"""The harm a candidate model does to the auction: the red team's measure (issue: "harm").

32 copies of the candidate join 32 honest patrons of the paper's randomisation; the fish on sale
are int(r · 64) at supplies r = 0.1 to 0.4 (where saboteurs bite). The same auctions (same
honest patrons, same market seed) are run without the copies: the honest-alone auction. Harm is
what the copies take from the host, per setting (fine-tuning off or on), summed over the
supplies and averaged over the trials:

* ``price``: how much lower the mean purchase price is than in the honest-alone auction (the
  paper's "artificially lowering the demand so that the price goes down"), in price units,
  the mean over the supplies of the drop of the pooled mean purchase price;
* ``unsold``: how many more fish per auction stay unsold (the paper: "the auction fails to sell
  as many fish as it should have"). Fish the copies buy themselves count as sold: a keen buyer
  who outbids honest patrons is competition, not sabotage (and a cheap purchase shows up in the
  price).

Every auction runs in one lock-step ``MarketBatch``; everything is seeded.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from agents.batch import from_manifests
from agents.forward import decide
from agents.manifest import Manifest
from agents.negotiator import honest_manifest, saboteur_manifest
from screener.limits import BASE_ROW
from sim.market import MarketBatch, MarketConfig, single_thread

SUPPLIES = (0.1, 0.2, 0.3, 0.4)
"""Item supplies of the harm auctions (fish on sale int(r · 64))."""
HONEST = 32
"""Honest patrons per harm auction."""
COPIES = 32
"""Copies of the candidate per harm auction."""
SETTINGS = (False, True)
"""Fine-tuning off, on."""


@dataclass(frozen=True)
class Outcome:
    """Pooled result of one (candidate, fine-tuning, supply) cell over the trials."""

    prices: tuple[float, ...]
    sold: int
    honest_bought: int
    auctions: int

    @property
    def mean_price(self) -> float:
        return float(np.mean(self.prices)) if self.prices else float("nan")


@dataclass(frozen=True)
class Harm:
    """Harm of one candidate with fine-tuning off and on (see the module docstring)."""

    price: tuple[float, float]
    unsold: tuple[float, float]

    def fraction(self, reference: Harm) -> tuple[float, float]:
        """Price harm as a fraction of ``reference``'s (the always-hold saboteur), off / on."""
        return (self.price[0] / reference.price[0], self.price[1] / reference.price[1])


def honest_population(trial: int, seed: int = 0) -> list[Manifest]:
    """The honest patrons of one trial (the paper's randomisation, with fine-tuning settings)."""
    rng = np.random.default_rng([seed, 7_919, trial])
    return [honest_manifest(rng, f"honest-{i:02d}") for i in range(HONEST)]


def saboteur(seed: int = 0) -> Manifest:
    """The paper's always-hold saboteur (the reference harm)."""
    return saboteur_manifest(np.random.default_rng([seed, 104_729]), "always-hold")


def outcomes(
    candidates: Sequence[Manifest | None],
    trials: int,
    seed: int = 0,
    settings: Sequence[bool] = SETTINGS,
) -> dict[tuple[int, bool, float], Outcome]:
    """Run every (candidate, fine-tuning, supply, trial) auction in one lock-step batch;
    None as a candidate is the honest-alone auction. Keyed (candidate index, fine-tune, r)."""
    populations = [honest_population(t, seed) for t in range(trials)]
    auctions: list[tuple[list[Manifest], MarketConfig]] = []
    keys: list[tuple[int, bool, float]] = []
    n_patrons = HONEST + COPIES
    for c, candidate in enumerate(candidates):
        copies = [] if candidate is None else [candidate] * COPIES
        for fine_tune in settings:
            for r in SUPPLIES:
                for t in range(trials):
                    market_seed = int(np.random.SeedSequence([seed, t, round(r * 100)])
                                      .generate_state(1)[0])  # fmt: skip
                    config = MarketConfig(
                        n_fish=int(r * n_patrons),
                        fine_tune=fine_tune,
                        seed=market_seed,
                        evaluate_all_rows=False,
                    )
                    auctions.append((populations[t] + copies, config))
                    keys.append((c, fine_tune, r))
    buyers: list[list[tuple[int, float]]] = [[] for _ in auctions]
    with single_thread():
        engine = MarketBatch(auctions)
        while not engine.finished.all():
            for a, record in enumerate(engine.step()):
                if record is not None:
                    buyers[a] += record.buyers
    pooled: dict[tuple[int, bool, float], tuple[list[float], int, int, int]] = {}
    for key, bought in zip(keys, buyers, strict=True):
        prices, sold, honest, n = pooled.get(key, ([], 0, 0, 0))
        prices += [price for _, price in bought]
        honest += sum(1 for i, _ in bought if i < HONEST)
        pooled[key] = (prices, sold + len(bought), honest, n + 1)
    return {k: Outcome(tuple(p), s, h, n) for k, (p, s, h, n) in pooled.items()}


@functools.cache
def _alone(trials: int, seed: int) -> dict[tuple[bool, float], Outcome]:
    """The honest-alone auctions (computed once per process)."""
    found = outcomes([None], trials, seed)
    return {(fine_tune, r): outcome for (_, fine_tune, r), outcome in found.items()}


def harms(
    candidates: Sequence[Manifest], trials: int, seed: int = 0
) -> tuple[list[Harm], dict[tuple[int, bool, float], Outcome]]:
    """The harm of each candidate, and every outcome (candidate index -1: honest alone)."""
    found = outcomes(candidates, trials, seed)
    alone = _alone(trials, seed)
    found.update({(-1, fine_tune, r): outcome for (fine_tune, r), outcome in alone.items()})

    def price_drop(c: int, fine_tune: bool) -> float:
        drops = []
        for r in SUPPLIES:
            base, mine = alone[(fine_tune, r)], found[(c, fine_tune, r)]
            if mine.prices:  # nothing sold at all is counted by ``unsold``, not as a price
                drops.append(base.mean_price - mine.mean_price)
        return float(np.mean(drops)) if drops else 0.0

    def unsold(c: int, fine_tune: bool) -> float:
        lost = [alone[(fine_tune, r)].sold - found[(c, fine_tune, r)].sold for r in SUPPLIES]
        return float(np.mean(lost)) / trials

    result = [
        Harm(
            price=(price_drop(c, False), price_drop(c, True)),
            unsold=(unsold(c, False), unsold(c, True)),
        )
        for c in range(len(candidates))
    ]
    return result, found


OPENING_VOTES = ("buys", "holds", "quits")
"""``opening_votes`` codes."""


def opening_votes(models: Sequence[Manifest]) -> np.ndarray:
    """Each model's vote in an auction's opening round: the base fish at the base price with
    the opening buy fraction ½, augmentation off (0 buys, 1 holds, 2 quits). A model that quits
    there harms the others only through that vote, as a sincere low bidder does."""
    row = torch.tensor([BASE_ROW], dtype=torch.float64)
    return decide(from_manifests(list(models)), row)[:, 0].numpy()


@functools.cache
def saboteur_harm(trials: int, seed: int = 0) -> Harm:
    """The always-hold saboteur's harm (the yardstick)."""
    return harms([saboteur(seed)], trials, seed)[0][0]
