"""Remote fine-tuning rounds: the round an auction leaves pending (``FineTuneRound``) and
closing it with the updates the patrons bring back (only their weights and biases may change:
``sim.market.design``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from agents.batch import from_manifests
from agents.manifest import Manifest
from sim.market.design import round_update_problems
from sim.market.randomness import round_seeds

if TYPE_CHECKING:
    from sim.market.engine import MarketBatch


@dataclass(frozen=True)
class FineTuneRound:
    """A fine-tuning round awaiting the patrons' results (remote mode)."""

    iteration: int
    """The iteration it follows."""
    rows: np.ndarray
    """(R, 8) float64: the item rows after that iteration (new price and buy fractions)."""
    fine_tune_seed: int
    augmentation_seed: int
    patrons: list[int]
    """Positions of the patrons asked (the active ones)."""


def pending_round(engine: MarketBatch, auction: int) -> FineTuneRound | None:
    """The auction's fine-tuning round awaiting ``apply_round``, if any."""
    if not engine.pending[auction]:
        return None
    iteration = int(engine.iteration[auction]) - 1
    fine_tune_seed, augmentation_seed = round_seeds(engine.configs[auction].seed, iteration)
    mine = slice(engine.first[auction], engine.first[auction + 1])
    return FineTuneRound(
        iteration=iteration,
        rows=engine.rows[auction].numpy().copy(),
        fine_tune_seed=fine_tune_seed,
        augmentation_seed=augmentation_seed,
        patrons=np.flatnonzero(engine.active[mine]).tolist(),
    )


def apply_round(engine: MarketBatch, auction: int, updates: Mapping[int, Manifest]) -> None:
    """Close the auction's pending round: patron ``position`` takes the weights and biases of
    ``updates[position]``; the others keep theirs. Raises ValueError (nothing applied) for a
    patron not asked in the round or an update that changes more than the numbers."""
    pending = pending_round(engine, auction)
    if pending is None:
        raise ValueError(f"auction {auction} has no pending fine-tuning round")
    index = []
    for position, manifest in updates.items():
        if position not in pending.patrons:
            raise ValueError(f"patron {position} is not asked in this round")
        i = int(engine.first[auction]) + position
        problems = round_update_problems(
            engine.entered(auction, position),
            manifest,
            current_design=engine.design(auction, position),
        )
        if problems:
            raise ValueError(f"patron {position}: {problems[0][0]}: {problems[0][1]}")
        index.append(i)
    if index:
        new = from_manifests([updates[p] for p in updates], engine.batch.dtype).parameters()
        engine.set_parameters(torch.tensor(index), new)
    engine.pending[auction] = False
