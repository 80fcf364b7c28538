"""Remote fine-tuning rounds: the round an auction leaves pending (``FineTuneRound``), the
updates the patrons bring back (only their weights and biases may change), and closing it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from agents.batch import from_manifests, to_manifest
from agents.manifest import Manifest
from sim.market.randomness import round_seeds

if TYPE_CHECKING:
    from sim.market.engine import MarketBatch

FROZEN_IN_ROUNDS = "only weights and biases change in a fine-tuning round"


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


def round_update_problems(current: Manifest, update: Manifest) -> list[tuple[str, str]]:
    """What ``update`` changes beyond the weights and biases of ``current``, as (dotted path,
    message) pairs: a fine-tuning round moves the numbers, never the model's design
    (activations, augmentation, settings, names)."""
    return design_changes(current.model_dump(mode="json"), update.model_dump(mode="json"))


def design_changes(current: dict[str, Any], update: dict[str, Any]) -> list[tuple[str, str]]:
    """``round_update_problems`` on the manifests' JSON forms."""
    problems: list[tuple[str, str]] = []

    def walk(before: Any, after: Any, path: tuple[str, ...]) -> None:
        if path[-1:] == ("bias",) or path[-2:-1] == ("weights",):
            return
        if isinstance(before, dict) and isinstance(after, dict) and before.keys() == after.keys():
            for key in before:
                walk(before[key], after[key], (*path, key))
        elif before != after:
            problems.append((".".join(path), f"{FROZEN_IN_ROUNDS}: must stay {before!r}"))

    walk(current, update, ())
    return problems


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
        problems = round_update_problems(to_manifest(engine.batch, i), manifest)
        if problems:
            raise ValueError(f"patron {position}: {problems[0][0]}: {problems[0][1]}")
        index.append(i)
    if index:
        new = from_manifests([updates[p] for p in updates], engine.batch.dtype).parameters()
        engine.set_parameters(torch.tensor(index), new)
    engine.pending[auction] = False
