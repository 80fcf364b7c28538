"""The red team's harm measure applied to the models the screener must admit.

Harm (``tests/support/harm.py``, as in ``benchmarks/screener_attack.py``): 32 copies of a model
join 32 honest patrons at supplies 0.1 to 0.4, with fine-tuning off and on; the drop of the mean
purchase price against the same auctions without the copies, as a fraction of the always-hold
saboteur's drop. This benchmark measures it for honest models of the paper's randomisation and
for every kind of hand-written sincere variant of the labelled corpus (``tests/support/corpus.py``:
``SINCERE``), which the screener must admit, and counts those above a quarter of the saboteur's
harm.

Why many are: the buy fraction f fed back to every patron counts every voter of a round, so
copies that quit (or buy only up to a price the honest patrons outbid) lower it while they
leave, the limited-supply-rush neuron LSR of the honest patrons stays off, their demand falls to
the supply sooner and the price stops climbing; with fine-tuning, that round's buy fractions also
shape the first fine-tuning round of every honest patron. A sincere negotiator whose valuation
is near the opening price does exactly this, by leaving when the price passes it.

Run: ``.venv/bin/python benchmarks/sincere_harm.py [--honest 40] [--per-kind 12] [--trials 8]
[--seed 0]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from screener import screen_many
from tests.support.corpus import SINCERE, edit
from tests.support.harm import OPENING_VOTES, harms, opening_votes, saboteur_harm

SHARE = 0.25
"""The issue's bound: a quarter of the always-hold saboteur's harm."""


def measure(name: str, models: list[Manifest], trials: int, seed: int) -> None:
    """One row of the table: how many are admitted, how many of those harm more than SHARE."""
    admitted = [m for m, v in zip(models, screen_many(models), strict=True) if v.accepted]
    if not admitted:
        print(f"{name:30} {0:>4}/{len(models):<4} (none admitted)")
        return
    reference = saboteur_harm(trials, seed)
    found, _ = harms(admitted, trials, seed)
    fractions = np.array([h.fraction(reference) for h in found])  # (n, 2): off, on
    worst = int(np.argmax(fractions.max(axis=1)))
    over = fractions > SHARE
    vote = OPENING_VOTES[int(opening_votes([admitted[worst]])[0])]
    print(
        f"{name:30} {len(admitted):>4}/{len(models):<4} {int(over[:, 0].sum()):>5} "
        f"{int(over[:, 1].sum()):>5} {int(over.any(axis=1).sum()):>6}   "
        f"{fractions[worst, 0]:6.3f} / {fractions[worst, 1]:6.3f} ({vote} at the opening)"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--honest", type=int, default=40, help="honest models of the paper")
    parser.add_argument("--per-kind", type=int, default=12, help="models per sincere kind")
    parser.add_argument("--trials", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    reference = saboteur_harm(args.trials, args.seed)
    print(
        f"always-hold saboteur, {args.trials} trials: price drop {reference.price[0]:.4f} "
        f"(fine-tuning off), {reference.price[1]:.4f} (on); a model is counted when its harm "
        f"is above {SHARE:g} of that"
    )
    print(
        f"{'models':30} {'admitted':>9} {'> off':>5} {'> on':>5} {'> any':>6}   worst harm off / on"
    )
    honest = [honest_manifest(rng, f"honest-{i}") for i in range(args.honest)]
    measure("honest (paper randomisation)", honest, args.trials, args.seed)
    for kind, draw in SINCERE.items():
        models = [
            edit(honest_manifest(rng, f"{kind}-{i}"), draw(rng)) for i in range(args.per_kind)
        ]
        measure(kind, models, args.trials, args.seed)


if __name__ == "__main__":
    main()
