"""The screener on the labelled corpus: confusion table per construction, speed, and how far
legitimate fine-tuning moves honest weights (the margin the tolerances must leave).

Prints:
* the confusion table per construction of the labelled corpus (``tests/support/corpus.py``:
  honest kinds, hand-written sincere variants, saboteur constructions, the red team's finds;
  honest kinds: accepted should be all; saboteur kinds: rejected should be all) with the rules
  that fired most for each kind;
* overall honest acceptance (target ≥ 99.5%) and saboteur rejection (target ≥ 99%);
* ``screen(manifest)`` one at a time: ms per manifest p50 / p99;
* ``screen_many`` per batch size 1, 16 and 64 (the screening process judges up to 16 queued
  submissions at once; re-screening a round of 64 fine-tuned patrons is ``rescreen``): the
  best of ``--repeats`` means of repeated calls after a warm-up, for honest manifests straight
  from the factory, for the same parsed from JSON as ``/submit`` receives them, for their
  fine-tuned versions screened at the door, for fine-tuned honest patrons re-screened
  (``rescreen``: no fine-tuning projection), and for a worst case where every model holds
  somewhere on the decisive row (each one runs the market-impact test auctions);
* with ``--legal-max N``: N honest models at the largest legal fine-tuning settings (lr 1e-3,
  4 epochs, batch 1): how many the door refuses, which rules their projected versions fail,
  whether those hold, and the price their copies leave in the test auctions;
* fine-tuning drift: 200 honest patrons fine-tuned with the most aggressive honest settings
  (lr 1e-4, 2 epochs, batch 4) for 4, 8 and 16 rounds, at auction prices, at falling and at
  rising prices: the largest weight change per layer and the share still accepted (4 rounds
  is what an auction allows).

Run: ``.venv/bin/python benchmarks/screener.py [--honest 1000] [--sincere 40] [--per-kind 8]
[--seed 0] [--speed-only] [--repeats 5] [--legal-max N]``. One thread; wall-clock timings are
noisy when other jobs share the machine (the best of several is the least disturbed), so the
process's CPU time is printed beside them.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from agents.batch import from_manifests
from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from screener import rescreen, screen, screen_many
from screener.checks import cheap_checks, failed_any
from screener.limits import DEMAND_SHARPNESS_LIMIT, NOISE_GATE_SHIFT
from screener.noisy import gate as noisy_gate
from screener.rules.numbers import Numbers
from screener.rules.sensors import demand_gain
from tests.support.corpus import (
    FALLING_PRICES,
    FINE_TUNE_ROUNDS,
    MAX_HONEST_FINE_TUNING,
    RISING_PRICES,
    ROUND_PRICES,
    corpus,
    edit,
    fine_tuned,
    red_team_corpus,
    sincere_corpus,
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


def confusion(seed: int, n_honest: int, per_sincere: int, per_kind: int) -> None:
    start = time.perf_counter()
    entries = corpus(seed, n_honest, per_kind)
    entries += sincere_corpus(np.random.default_rng([seed, 1]), per_sincere) + red_team_corpus()
    built = time.perf_counter() - start
    start = time.perf_counter()
    verdicts = []
    for i in range(0, len(entries), 64):
        verdicts += screen_many([e.manifest for e in entries[i : i + 64]])
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
    sincere = [e.manifest for e in entries if not e.saboteur]
    sharpest = max(demand_sharpness(sincere))
    print(
        f"sharpest reaction of an honest or sincere sensor to the buy fraction: "
        f"{sharpest:.3g} per unit of f (demand-sharpness allows {DEMAND_SHARPNESS_LIMIT:g})"
    )
    moved = max(
        float(noisy_gate(from_manifests(sincere[i : i + 64])).shift.max())
        for i in range(0, len(sincere), 64)
    )
    print(
        "most an honest or sincere model's own noise moves a decision score through a sensor: "
        f"{moved:.3g} (noise-gate allows {NOISE_GATE_SHIFT:g})"
    )


def demand_sharpness(manifests: list[Manifest]) -> list[float]:
    """Each model's sharpest reaction of PG, SZ or ST to the buy fraction, as
    ``demand-sharpness`` weighs it."""
    out: list[float] = []
    for i in range(0, len(manifests), 64):
        out += demand_gain(Numbers.of(from_manifests(manifests[i : i + 64]))).max(axis=1).tolist()
    return out


def speed(seed: int) -> None:
    rng = np.random.default_rng(seed)
    manifests = corpus(seed, 100, 2)
    sample = [manifests[int(i)].manifest for i in rng.integers(len(manifests), size=200)]
    for m in sample[:20]:
        screen(m)  # warm-up
    wall, cpu = [], []
    for m in sample:
        start, start_cpu = time.perf_counter(), time.process_time()
        screen(m)
        wall.append((time.perf_counter() - start) * 1e3)
        cpu.append((time.process_time() - start_cpu) * 1e3)
    print(f"\nscreen(), one manifest at a time ({len(sample)} corpus manifests):")
    for name, times in (("wall", wall), ("CPU", cpu)):
        times.sort()
        p50, p99 = statistics.median(times), times[int(0.99 * (len(times) - 1))]
        print(f"  {name:>4} time: p50 {p50:.2f} ms, p99 {p99:.2f} ms")


BATCH_SIZES = (1, 16, 64)


def _holders(rng: np.random.Generator, n: int) -> list[Manifest]:
    """Models that hold somewhere on the reachable decisive row and pass the rules and probes
    (honest factory models with a large hold bias): each runs the market-impact test."""
    found: list[Manifest] = []
    while len(found) < n:
        models = [honest_manifest(rng, f"holder-{len(found)}-{i}") for i in range(256)]
        batch = from_manifests(models)
        cheap = cheap_checks(batch)
        keep = cheap.holds & ~failed_any(cheap.groups)
        found += [m for m, k in zip(models, keep, strict=True) if k]
    return found[:n]


def _timed(call: Callable[[], object], calls: int, repeats: int) -> tuple[float, float]:
    """Wall and CPU ms per call after one warm-up call: the best of ``repeats`` means over
    ``calls`` calls (a shared machine only ever adds time)."""
    call()
    best = (float("inf"), float("inf"))
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        for _ in range(calls):
            call()
        wall = (time.perf_counter() - start) * 1e3 / calls
        cpu = (time.process_time() - start_cpu) * 1e3 / calls
        best = min(best, (wall, cpu))
    return best


def batch_costs(seed: int, repeats: int) -> None:
    rng = np.random.default_rng(seed)
    made = [honest_manifest(rng, f"h{i}") for i in range(max(BATCH_SIZES))]
    parsed = [Manifest.model_validate_json(m.model_dump_json()) for m in made]
    tuned = fine_tuned(made, rng)
    tuned_batch = from_manifests(tuned)
    holders = _holders(rng, max(BATCH_SIZES))
    cases: dict[str, Callable[[int], Callable[[], object]]] = {
        "factory-made": lambda n: lambda: screen_many(made[:n]),
        "parsed from JSON": lambda n: lambda: screen_many(parsed[:n]),
        "fine-tuned, at the door": lambda n: lambda: screen_many(tuned[:n]),
        "rescreen fine-tuned": lambda n: lambda: rescreen(tuned_batch.select(np.arange(n))),
        "all holders": lambda n: lambda: screen_many(holders[:n]),
    }
    print(f"\nscreen_many() per batch size (best of {repeats} means of repeated calls after a "
          "warm-up): ms per call, ms per manifest, wall (CPU)")  # fmt: skip
    print(f"{'case':>20} " + " ".join(f"{f'batch {n}':>26}" for n in BATCH_SIZES))
    for name, make in cases.items():
        row = []
        for n in BATCH_SIZES:
            calls = max(3, 160 // n) if name != "all holders" else max(2, 16 // n)
            wall, cpu = _timed(make(n), calls, repeats)
            row.append(f"{wall:7.1f} ({cpu:6.1f}) {wall / n:5.2f} ms")
        print(f"{name:>20} " + " ".join(f"{cell:>26}" for cell in row))


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


LARGEST_LEGAL = {"epochs": 4, "batch_size": 1, "learning_rate": 1e-3}
"""The largest fine-tuning settings the ``fine-tuning`` rule admits (batch 1: the most steps)."""


def largest_legal(seed: int, n: int) -> None:
    """Honest models at the largest legal fine-tuning settings: how many the door refuses, why,
    and what their projected versions do (hold? their copies' price in the test auctions)."""
    from agents.batch import to_manifest
    from screener import impact

    rng = np.random.default_rng([seed, 2])
    models = [
        edit(honest_manifest(rng, f"max-{i}"), {"fine_tuning": LARGEST_LEGAL}) for i in range(n)
    ]
    verdicts = screen_many(models)
    tuned = impact.project(from_manifests(models))
    cheap = cheap_checks(tuned)
    rules: Counter[str] = Counter()
    for k in range(n):
        for group in cheap.groups:
            rules.update(
                f"{group.rules[c]}:{group.neurons[c]}" for c in np.flatnonzero(group.failed[k])
            )
    outcomes = impact.run([to_manifest(tuned, k) for k in range(n)])
    prices = [o.mean_price for o in outcomes]
    refused = sum(not v.accepted for v in verdicts)
    print(f"\n{n} honest models at lr 1e-3, 4 epochs, batch 1: {refused} "
          f"refused at the door; their versions after {impact.rounds()} projected rounds fail "
          f"{dict(rules.most_common())}; hold clean {int(cheap.probed.holds.sum())}, noisy "
          f"{int(cheap.noisy.holds.sum())}; their copies leave {min(prices):.4f}-{max(prices):.4f} "
          f"in the test auctions (bar {impact.references().lowest_price:.4f})")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--honest", type=int, default=1000)
    parser.add_argument("--sincere", type=int, default=40)
    parser.add_argument("--per-kind", type=int, default=8)
    parser.add_argument("--no-drift", action="store_true", help="skip the fine-tuning drift")
    parser.add_argument(
        "--speed-only", action="store_true", help="only the batch costs (no corpus, no drift)"
    )
    parser.add_argument("--repeats", type=int, default=5, help="best of this many timings")
    parser.add_argument(
        "--legal-max", type=int, default=0, help="also judge N models at the largest legal settings"
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.legal_max:
        largest_legal(args.seed, args.legal_max)
    if args.speed_only:
        batch_costs(args.seed, args.repeats)
        return
    confusion(args.seed, args.honest, args.sincere, args.per_kind)
    speed(args.seed)
    batch_costs(args.seed, args.repeats)
    if not args.no_drift:
        drift(args.seed)


if __name__ == "__main__":
    main()
