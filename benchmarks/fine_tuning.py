"""One fine-tuning round of 64 patrons: its time, and whether each patron's result equals its
fine-tuning alone (what a faithful remote agent computes), bit for bit.

Two populations: the paper's honest patrons (batch sizes 4-15, 5 copies) and patrons of every
batch size (1-64) and copy count (1-16) the screener admits. The round is
``agents.fine_tuning.fine_tune_round`` on the 64 at once (best of ``--repeats``, one torch
thread, CPU time), then on each patron alone; the largest parameter difference between the two
is printed (0: bit for bit).

Run: ``.venv/bin/python benchmarks/fine_tuning.py [--repeats 5]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from agents.batch import PARAMETERS, FSNBatch, from_manifests
from agents.fine_tuning import fine_tune_round
from agents.manifest import Augmentation, FineTuning, Manifest
from agents.negotiator import honest_manifest
from sim.market import MarketConfig, item_rows

PATRONS = 64


def populations() -> dict[str, list[Manifest]]:
    rng = np.random.default_rng(0)
    paper = [honest_manifest(rng, f"h{i}") for i in range(PATRONS)]
    varied = [
        honest_manifest(rng, f"v{i}").model_copy(
            update={
                "augmentation": Augmentation(copies=int(rng.integers(1, 17)), noise_std=0.02),
                "fine_tuning": FineTuning(
                    epochs=int(rng.integers(1, 5)),
                    batch_size=int(rng.integers(1, 65)),
                    learning_rate=1e-4,
                ),
            }
        )
        for i in range(PATRONS)
    ]
    return {"paper's patrons": paper, "every batch size and copy count": varied}


def round_of(batch: FSNBatch, rows: torch.Tensor, positions: list[int]) -> FSNBatch:
    n = len(positions)
    return fine_tune_round(
        batch,
        rows,
        np.full(n, 11, dtype=np.uint64),
        np.full(n, 12, dtype=np.uint64),
        np.array(positions),
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows = torch.from_numpy(item_rows(MarketConfig(n_fish=1), np.random.default_rng(1)))
    print("| patrons | one round of 64, ms | largest difference from each alone |")
    print("|---|---|---|")
    for name, manifests in populations().items():
        batch = from_manifests(manifests)
        best = float("inf")
        for _ in range(args.repeats):
            started = time.process_time()
            together = round_of(batch, rows, list(range(PATRONS)))
            best = min(best, time.process_time() - started)
        worst = 0.0
        for p in range(PATRONS):
            alone = round_of(batch.select([p]), rows, [p])
            for name_ in PARAMETERS:
                gap = (getattr(alone, name_)[0] - getattr(together, name_)[p]).abs().max()
                worst = max(worst, float(gap))
        print(f"| {name} | {best * 1e3:.1f} | {worst:.1e} |")


if __name__ == "__main__":
    main()
