"""How many honest models the screener refuses at the manifest's legal extremes: the paper's
honest randomisation (factory draws, half of them fine-tuning), one sensor's sharpness ``a``
multiplied by a factor, the augmentation's noise and copies set, every combination screened as
the server screens it and reviewed with the server's margin. Prints, per combination, the count
accepted / held / refused and the rules that refused.

The honest design's sensors read their thresholds at the design's sharpness; the rules allow
sharper ones (``demand-sharpness``, ``off-design-input``) and the manifest any ``noise_std`` up
to 0.05 on 1 to 16 copies. ``noise-gate`` compares each sensor clean with its reading averaged
over the model's noisy copies, so a threshold much sharper than its own noise moves by more
than the bar near its edge, honest or not (docs/screener.md, *Conditions the screener does not
test*).

    .venv/bin/python benchmarks/noise_extremes.py [--draws 100] [--seed 12345]
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path[:] = [entry for entry in sys.path if Path(entry or ".").resolve() != HERE]
sys.path.append(str(HERE.parent))

from agents.manifest import Manifest, parse_manifest  # noqa: E402
from agents.negotiator import honest_manifest  # noqa: E402
from screener import review, screen_many  # noqa: E402

REVIEW_MARGIN = 0.005
"""The server's default ``SRD_REVIEW_MARGIN``."""

GRID = [
    ("PG", 1.0, 2, 0.05),
    ("PG", 2.0, 2, 0.05),
    ("PG", 3.0, 2, 0.05),
    ("PG", 3.0, 5, 0.05),
    ("PG", 3.0, 16, 0.05),
    ("PG", 3.0, 5, 0.01),
    ("PG", 5.0, 5, 0.05),
    ("PG", 5.0, 5, 0.01),
    ("SZ", 2.0, 5, 0.05),
    ("SZ", 3.0, 5, 0.05),
    ("SZ", 4.0, 5, 0.05),
    ("SZ", 7.0, 5, 0.05),
    ("SZ", 7.0, 5, 0.01),
]
"""(sensor, factor on its ``a``, copies, noise_std): the design (×1) at the noise's extreme,
then sharper sensors at that extreme and at the default σ 0.01."""


def varied(base: list[dict], sensor: str, factor: float, copies: int, std: float) -> list[Manifest]:
    manifests = []
    for document in base:
        changed = copy.deepcopy(document)
        changed["external_sensor"][sensor]["activation"]["a"] *= factor
        changed["augmentation"] |= {"copies": copies, "noise_std": std}
        manifests.append(parse_manifest(changed))
    return manifests


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=100, help="honest factory draws")
    parser.add_argument("--seed", type=int, default=12345)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    base = [
        honest_manifest(rng, f"honest-{i}", fine_tune=i % 2 == 0).model_dump(mode="json")
        for i in range(args.draws)
    ]
    print(f"{args.draws} honest draws (seed {args.seed}), review margin {REVIEW_MARGIN}")
    print("sensor  a ×  copies  σ     accepted  held  refused  refusing rules")
    for sensor, factor, copies, std in GRID:
        started = time.perf_counter()
        verdicts = screen_many(varied(base, sensor, factor, copies, std))
        outcomes = Counter(review(v, REVIEW_MARGIN) for v in verdicts)
        rules = Counter(
            f"{r.rule} {r.neuron}"
            for v in verdicts
            if review(v, REVIEW_MARGIN) == "refused"
            for r in v.reasons
        )
        named = ", ".join(f"{rule} ({n})" for rule, n in rules.most_common()) or "-"
        print(
            f"{sensor:<7} {factor:<4g} {copies:<7} {std:<5g} {outcomes['accepted']:<9} "
            f"{outcomes['held']:<5} {outcomes['refused']:<8} {named}"
            f"   [{time.perf_counter() - started:.1f} s]",
            flush=True,
        )


if __name__ == "__main__":
    main()
