"""The screener on the labelled corpus: confusion table per construction, speed, and how far
legitimate fine-tuning moves honest weights (the margin the tolerances must leave).

Prints:
* the confusion table per construction (honest kinds: accepted should be all; saboteur kinds:
  rejected should be all) with the rules that fired most for each saboteur kind;
* overall honest acceptance (target ≥ 99.5%) and saboteur rejection (target ≥ 99%);
* ``screen(manifest)`` one at a time: ms per manifest p50 / p99 and manifests/s (target
  ≤ 5 ms per manifest), and ``screen_many`` in batches of 64 (re-screening a market);
* ``screen_many`` per batch size 1 to 64 (the screening process judges up to 16 queued
  submissions at once): mean ms per call over at least 200 calls after a warm-up, for honest
  manifests straight from the factory and for the same manifests parsed from JSON as ``/submit``
  receives them (parsed manifests share no sub-models, so building the batch costs more);
* fine-tuning drift: 200 honest patrons fine-tuned with the most aggressive honest settings
  (lr 1e-4, 2 epochs, batch 4) for 4, 8 and 16 rounds, at auction prices, at falling and at
  rising prices: the largest weight change per layer and the share still accepted (4 rounds
  is what an auction allows).

Run: ``.venv/bin/python benchmarks/screener.py [--honest 1000] [--per-kind 8] [--seed 0]``.
One thread; wall-clock timings are noisy when other jobs share the machine, so the process's
CPU time per manifest is printed beside them (it excludes time spent waiting for a core).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from agents.manifest import Manifest
from agents.negotiator import from_manifests, honest_manifest
from screener import screen, screen_many
from tests.screener.corpus import (
    FALLING_PRICES,
    FINE_TUNE_ROUNDS,
    MAX_HONEST_FINE_TUNING,
    RISING_PRICES,
    ROUND_PRICES,
    corpus,
    edit,
    fine_tuned,
)

REGIMES = {
    "4.8-5.6": ROUND_PRICES,
    "falling 4.8-4.9": FALLING_PRICES,
    "rising 5.3-6.0": RISING_PRICES,
}
"""Prices of the fine-tuning rounds: anywhere the auction moves, while it falls, while it rises."""
LAYERS = {
    "ES weights": "es_weight",
    "ES biases": "es_bias",
    "FC": "fc_weight",
    "FC biases": "fc_bias",
    "PFC judgements": "judgement_weight",
    "PFC verdicts": "verdict_weight",
}


def confusion(seed: int, n_honest: int, per_kind: int) -> None:
    start = time.perf_counter()
    entries = corpus(seed, n_honest, per_kind)
    built = time.perf_counter() - start
    start = time.perf_counter()
    verdicts = []
    for i in range(0, len(entries), 128):
        verdicts += screen_many([e.manifest for e in entries[i : i + 128]])
    judged = time.perf_counter() - start
    table: dict[tuple[bool, str], Counter[bool]] = defaultdict(Counter)
    fired: dict[str, Counter[str]] = defaultdict(Counter)
    for entry, verdict in zip(entries, verdicts, strict=True):
        table[(entry.saboteur, entry.construction)][verdict.accepted] += 1
        for rule in {f"{r.rule}:{r.neuron}" for r in verdict.reasons}:
            fired[entry.construction][rule] += 1
    print(f"corpus: {len(entries)} manifests (seed {seed}), built in {built:.1f} s, "
          f"screened in {judged:.2f} s")  # fmt: skip
    print(
        f"\n{'label':9} {'construction':36} {'n':>4} {'accepted':>8} {'rejected':>8}  rules fired"
    )
    for (saboteur, kind), counts in sorted(table.items()):
        top = ", ".join(f"{rule} ({n})" for rule, n in fired[kind].most_common(3))
        label = "saboteur" if saboteur else "honest"
        n = counts[True] + counts[False]
        print(f"{label:9} {kind:36} {n:4d} {counts[True]:8d} {counts[False]:8d}  {top}")
    honest = [v.accepted for e, v in zip(entries, verdicts, strict=True) if not e.saboteur]
    caught = [not v.accepted for e, v in zip(entries, verdicts, strict=True) if e.saboteur]
    print(f"\nhonest accepted: {sum(honest)}/{len(honest)} = {sum(honest) / len(honest):.2%} "
          f"(target ≥ 99.5%)")  # fmt: skip
    print(f"saboteurs rejected: {sum(caught)}/{len(caught)} = {sum(caught) / len(caught):.2%} "
          f"(target ≥ 99%)")  # fmt: skip


def speed(seed: int) -> None:
    rng = np.random.default_rng(seed)
    manifests = corpus(seed, 100, 2)
    sample = [manifests[int(i)].manifest for i in rng.integers(len(manifests), size=400)]
    for m in sample[:20]:
        screen(m)  # warm-up
    wall, cpu = [], []
    for m in sample:
        start, start_cpu = time.perf_counter(), time.process_time()
        screen(m)
        wall.append((time.perf_counter() - start) * 1e3)
        cpu.append((time.process_time() - start_cpu) * 1e3)
    print(f"\nscreen(), one manifest at a time ({len(sample)} manifests; target ≤ 5 ms):")
    for name, times in (("wall", wall), ("CPU", cpu)):
        times.sort()
        p50, p99 = statistics.median(times), times[int(0.99 * (len(times) - 1))]
        rate = 1e3 / statistics.mean(times)
        print(f"  {name:>4} time: p50 {p50:.2f} ms, p99 {p99:.2f} ms, {rate:.0f} manifests/s")
    start = time.perf_counter()
    for i in range(0, len(sample), 64):
        screen_many(sample[i : i + 64])
    per = (time.perf_counter() - start) * 1e3 / len(sample)
    print(f"screen_many(), batches of 64: {per:.2f} ms per manifest, {1e3 / per:.0f} manifests/s")


BATCH_SIZES = (1, 2, 4, 8, 16, 32, 64)


def batch_costs(seed: int) -> None:
    rng = np.random.default_rng(seed)
    made = [honest_manifest(rng, f"h{i}") for i in range(max(BATCH_SIZES))]
    parsed = [Manifest.model_validate_json(m.model_dump_json()) for m in made]
    print("\nscreen_many() per batch size (mean of >= 200 calls; ms per call, ms per manifest):")
    print(f"{'batch':>6} {'factory-made':>22} {'parsed from JSON':>22}")
    for size in BATCH_SIZES:
        row = []
        for pool in (made, parsed):
            batch = pool[:size]
            screen_many(batch)  # warm-up
            calls = max(200, 2000 // size)
            start = time.perf_counter()
            for _ in range(calls):
                screen_many(batch)
            per_call = (time.perf_counter() - start) * 1e3 / calls
            row.append(f"{per_call:8.2f} ms {per_call / size:7.3f} ms")
        print(f"{size:6d} {row[0]:>22} {row[1]:>22}")


def drift(seed: int) -> None:
    settings = {"fine_tuning": MAX_HONEST_FINE_TUNING}
    print("\nfine-tuning drift: 200 honest patrons at lr 1e-4, 2 epochs, batch 4 (max |change|)")
    print(
        f"{'round prices':>14} {'rounds':>6} {'accepted':>9}  "
        + "  ".join(f"{k:>14}" for k in LAYERS)
    )
    for name, prices in REGIMES.items():
        rng = np.random.default_rng(seed + 1)
        honest = [edit(honest_manifest(rng, f"h{i}"), settings) for i in range(200)]
        before = from_manifests(honest)
        current, done = honest, 0
        for rounds in (4, 8, 16):
            while done < rounds:
                current = fine_tuned(current, rng, prices)
                done += FINE_TUNE_ROUNDS
            after = from_manifests(current)
            moved = [
                float((getattr(after, field) - getattr(before, field)).abs().max())
                for field in LAYERS.values()
            ]
            accepted = sum(v.accepted for v in screen_many(current))
            print(f"{name:>14} {rounds:6d} {accepted:5d}/{len(current)}  "
                  + "  ".join(f"{m:14.4f}" for m in moved))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--honest", type=int, default=1000)
    parser.add_argument("--per-kind", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    confusion(args.seed, args.honest, args.per_kind)
    speed(args.seed)
    batch_costs(args.seed)
    drift(args.seed)


if __name__ == "__main__":
    main()
