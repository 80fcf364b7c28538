"""Lavaland speed: batched evaluation vs a per-map loop, and one SRD epoch.

Targets on a 2-core machine (paper preset, 4 plans per map): 4096 maps evaluated in ≤ 5 s;
one SRD epoch over 4096 maps (one map per SGD step) in ≤ 60 s.

    .venv/bin/python benchmarks/lavaland.py [--maps 4096] [--loop-maps 256] [--preset paper]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from agents.robot2nn import PRESETS
from sim.lavaland.engine import PROJECTS, build_model, evaluate, explore_coins, make_maps
from sim.lavaland.training import train_srd


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--maps", type=int, default=4096)
    parser.add_argument("--loop-maps", type=int, default=256, help="maps timed in the loop")
    parser.add_argument("--preset", choices=list(PRESETS), default="paper")
    args = parser.parse_args()
    torch.set_num_threads(1)
    project = PROJECTS["A"]
    n_plans = PRESETS[args.preset].n_plans
    seen = make_maps(args.maps, project, np.random.default_rng([0, 0]))
    robot = build_model(project, args.preset)
    coins = explore_coins(np.random.default_rng([0, 2]), args.maps, n_plans)

    evaluate(robot, seen.select(slice(0, 64)), coins[:64])  # warm-up
    start = time.perf_counter()
    batched = evaluate(robot, seen, coins)
    batched_s = time.perf_counter() - start

    loop = args.loop_maps
    start = time.perf_counter()
    for i in range(loop):
        evaluate(robot, seen.select(i), coins[i : i + 1])
    loop_s = time.perf_counter() - start
    single = evaluate(robot, seen.select(slice(0, loop)), coins[:loop], chunk=1)
    assert np.array_equal(single.reached, batched.reached[:loop])

    start = time.perf_counter()
    rng = np.random.default_rng([0, 3])
    train_srd(robot, seen, rng.permutation(args.maps), explore_coins(rng, args.maps, n_plans), 1e-4)
    epoch_s = time.perf_counter() - start

    print(f"preset {args.preset}: {n_plans} plans per map, torch threads 1")
    print(
        f"batched evaluation: {args.maps} maps in {batched_s:.2f} s "
        f"= {args.maps / batched_s:,.0f} maps/s (target: {args.maps} maps ≤ 5 s), "
        f"accuracy {batched.accuracy:.3f}"
    )
    print(f"per-map loop:       {loop} maps in {loop_s:.2f} s = {loop / loop_s:,.0f} maps/s")
    print(f"speed-up batched / per-map: {(args.maps / batched_s) / (loop / loop_s):.1f}×")
    print(
        f"SRD epoch: {args.maps} maps (one SGD step each) in {epoch_s:.1f} s "
        f"= {1e3 * epoch_s / args.maps:.2f} ms per map (target ≤ 60 s)"
    )


if __name__ == "__main__":
    main()
