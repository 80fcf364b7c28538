"""Speed of the auction engine: batched patrons vs a plain per-patron loop, and the paper's grid.

1. One auction of 64 honest patrons at a time, ``sim.market.Market`` (all patrons in one tensor
   pass per iteration, fine-tuning batched over patrons) against ``loop_auction`` of
   tests/sim/test_market.py (the same auction, one patron at a time; the test suite checks
   that both give identical records). With and without fine-tuning, scoring every row each
   iteration (the reference) or only while rows can still feed fine-tuning (the study).
2. The lock-step engine ``MarketBatch`` (the study's path): many auctions per tensor pass.
3. The full grid of the paper: 9 rarities × 10 trials × fine-tune off/on × saboteurs 0/0.5 =
   360 auctions (``srd auction-study --grid``), wall-clock.

Targets: batched ≥ 50× the per-patron loop; the 360-auction grid in ≤ 30 s. One thread; other
work on the machine makes the numbers noisy: ratios are also given in CPU time. Every timed run
starts after a garbage collection (so it does not pay for the garbage of the setup); the loop
plays whole cycles of rarities; each lock-step batch is warmed up once on other auctions, then
timed, then the loop replays its auctions (by default all of them; records checked equal).

Run: ``.venv/bin/python benchmarks/market.py [--loop-auctions N] [--no-grid]``
"""

from __future__ import annotations

import argparse
import gc
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # for tests.support

from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from sim.market import IterationRecord, Market, MarketBatch, MarketConfig
from studies.auctions import StudyConfig, run_study
from tests.support.loops import loop_auction

torch.set_num_threads(1)
PATRONS = 64
RARITIES = (0.1, 0.3, 0.5, 0.7, 0.9)
WARM_UP = 10
"""Auctions of the untimed lock-step run before each timed one."""


Work = list[tuple[list[Manifest], MarketConfig]]


def workload(n: int, fine_tune: bool, all_rows: bool, first: int = 0) -> Work:
    """n auctions of 64 honest patrons (numbered from ``first``), rarities cycling through
    RARITIES."""
    out = []
    for k in range(first, first + n):
        rng = np.random.default_rng(1000 + k)
        manifests = [honest_manifest(rng, f"h{i}", fine_tune=fine_tune) for i in range(PATRONS)]
        rarity = RARITIES[k % len(RARITIES)]
        config = MarketConfig(
            n_fish=int(rarity * PATRONS), fine_tune=fine_tune, seed=k, evaluate_all_rows=all_rows
        )
        out.append((manifests, config))
    return out


Run = Callable[[list[Manifest], MarketConfig], list[IterationRecord]]


def rate(run: Run, auctions: Work) -> tuple[float, float, list[list[IterationRecord]]]:
    """Auctions per second of wall-clock and of this process's CPU time, and the records."""
    gc.collect()
    wall, cpu = time.perf_counter(), time.process_time()
    records = [run(m, c) for m, c in auctions]
    n = len(auctions)
    return n / (time.perf_counter() - wall), n / (time.process_time() - cpu), records


def one_at_a_time(n_loop: int, n_batched: int) -> None:
    """Market alone vs the loop."""
    print(f"one auction at a time, {PATRONS} patrons (auctions/s; wall-clock, then CPU time)")
    print(
        f"{'fine-tune':>9} {'rows':>9} {'batched':>9} {'loop':>9} {'ratio':>7} "
        f"{'cpu ratio':>9} {'iters':>6}"
    )
    for fine_tune in (False, True):
        for all_rows in (True, False):
            batched_work = workload(n_batched, fine_tune, all_rows)
            fast, fast_cpu, fast_records = rate(lambda m, c: list(Market(m, c).run()), batched_work)
            slow, slow_cpu, slow_records = rate(loop_auction, batched_work[:n_loop])
            assert slow_records == fast_records[:n_loop], "loop and batched auctions differ"
            iterations = np.mean([len(r) for r in fast_records])
            rows = "all" if all_rows else "decisive"
            print(
                f"{fine_tune!s:>9} {rows:>9} {fast:9.2f} {slow:9.3f} {fast / slow:6.1f}× "
                f"{fast_cpu / slow_cpu:8.1f}× {iterations:6.1f}"
            )


def run_lock_step(work: Work) -> list[list[IterationRecord]]:
    """Run the auctions in one MarketBatch; their records."""
    engine = MarketBatch(work)
    records: list[list[IterationRecord]] = [[] for _ in work]
    while not engine.finished.all():
        for mine, record in zip(records, engine.step(), strict=True):
            if record is not None:
                mine.append(record)
    return records


def lock_step(n: int, n_loop: int) -> None:
    """MarketBatch on n auctions vs the loop replaying n_loop of them, spread over the batch
    (every k-th, so the rarities stay balanced when n_loop divides n)."""
    print(
        f"\nlock-step MarketBatch (the study's engine), {n} auctions of {PATRONS} patrons, "
        f"decisive rows, against the loop on {n_loop} of them "
        "(auctions/s; ratios wall-clock and CPU)"
    )
    for fine_tune in (False, True):
        run_lock_step(workload(WARM_UP, fine_tune, all_rows=False, first=n))
        work = workload(n, fine_tune, all_rows=False)
        gc.collect()
        wall, cpu = time.perf_counter(), time.process_time()
        records = run_lock_step(work)
        speed = n / (time.perf_counter() - wall)
        speed_cpu = n / (time.process_time() - cpu)
        picked = list(range(0, n, max(1, n // n_loop)))[:n_loop]
        loop, loop_cpu, loop_records = rate(loop_auction, [work[i] for i in picked])
        assert loop_records == [records[i] for i in picked], "loop and lock-step auctions differ"
        print(
            f"  fine-tune {fine_tune!s:>5}: {speed:8.1f}   loop {loop:6.3f}   "
            f"{speed / loop:6.1f}×   cpu {speed_cpu / loop_cpu:6.1f}×"
        )


def grid() -> None:
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        result = run_study(StudyConfig(trials=10, grid=True), out_dir=Path(out))
        elapsed = time.perf_counter() - start
    print(f"\nfull grid: {result['auctions']} auctions in {elapsed:.1f} s (target ≤ 30 s)")
    print(f"{'setting':>26} {'rarity':>6} {'price':>7} {'rate':>6} {'buyers':>6}")
    for row in result["rows"]:
        price = "—" if row["mean_price"] is None else f"{row['mean_price']:.3f}"
        print(
            f"{row['setting']:>26} {row['rarity']:6.1f} {price:>7} "
            f"{row['purchase_rate']:6.3f} {row['buyer_fraction']:6.3f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--loop-auctions", type=int, default=len(RARITIES), help="auctions for the loop"
    )
    parser.add_argument("--batched-auctions", type=int, default=15, help="auctions, batched")
    parser.add_argument("--lock-step", type=int, default=90, help="auctions per MarketBatch")
    parser.add_argument(
        "--lock-step-loop",
        type=int,
        default=None,
        help="auctions of the MarketBatch that the loop replays (default all: the loop's time "
        "per auction varies a lot, ±35%% over 10 of them)",
    )
    parser.add_argument("--no-grid", action="store_true", help="skip the 360-auction grid")
    args = parser.parse_args()
    one_at_a_time(args.loop_auctions, args.batched_auctions)
    lock_step(args.lock_step, args.lock_step_loop or args.lock_step)
    if not args.no_grid:
        grid()


if __name__ == "__main__":
    main()
