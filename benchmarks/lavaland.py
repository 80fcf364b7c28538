"""Lavaland speed: batched evaluation vs a per-map loop, and one SRD epoch two ways.

Both SRD paths run on the same maps, order and coins: today's autograd step (``train_srd``)
and the fused compiled step (``train_srd_fused``). Printed: their times, the ratio, and the
largest difference of the 180 weights after 64, 256, 1024 and all steps. Targets on a 2-core
machine: 4096 maps × 4 plans evaluated in ≤ 5 s; a fused epoch over 4096 maps in ≤ 3 s and
≥ 10× the autograd path.

    .venv/bin/python benchmarks/lavaland.py [--maps 4096] [--loop-maps 256] [--preset paper]
        [--project A] [--loss-guard]
"""

from __future__ import annotations

import argparse
import itertools
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from agents.planning import PRESETS
from agents.robot2nn import Robot2NN
from sim.lavaland.engine import PROJECTS, build_model, evaluate, explore_coins, make_maps
from sim.lavaland.fused import train_srd_fused
from sim.lavaland.training import train_srd

CHECKPOINTS = (64, 256, 1024)
"""Steps after which the two paths' weights are compared (and after the whole epoch)."""


def epoch(
    trainer: Callable[..., Any], model: Robot2NN, *args: Any
) -> tuple[float, list[torch.Tensor]]:
    """Run one epoch in segments ending at the checkpoints; time and weights at each."""
    maps, order, coins, lr = args
    bounds = [0, *[c for c in CHECKPOINTS if c < len(order)], len(order)]
    weights, elapsed = [], 0.0
    for lo, hi in itertools.pairwise(bounds):
        start = time.perf_counter()
        trainer(model, maps, order[lo:hi], coins[lo:hi], lr)
        elapsed += time.perf_counter() - start
        weights.append(model.kernel_stack().detach().clone())
    return elapsed, weights


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--maps", type=int, default=4096)
    parser.add_argument("--loop-maps", type=int, default=256, help="maps timed in the loop")
    parser.add_argument("--preset", choices=list(PRESETS), default="paper")
    parser.add_argument("--project", choices=list(PROJECTS), default="A")
    parser.add_argument("--loss-guard", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    project = PROJECTS[args.project]
    n_plans = PRESETS[args.preset].n_plans
    seen = make_maps(args.maps, project, np.random.default_rng([0, 0]))
    robot = build_model(project, args.preset, loss_guard=args.loss_guard)
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

    rng = np.random.default_rng([0, 3])
    order, train_coins = rng.permutation(args.maps), explore_coins(rng, args.maps, n_plans)
    train_srd_fused(robot, seen.select(slice(0, 8)), np.arange(8), train_coins[:8], 1e-4)  # JIT
    today_s, today = epoch(
        train_srd,
        build_model(project, args.preset, loss_guard=args.loss_guard),
        seen,
        order,
        train_coins,
        1e-4,
    )
    fused_s, fused = epoch(
        train_srd_fused,
        build_model(project, args.preset, loss_guard=args.loss_guard),
        seen,
        order,
        train_coins,
        1e-4,
    )

    guard = "guarded loss" if args.loss_guard else "paper loss"
    print(f"project {args.project}, preset {args.preset}: {n_plans} plans per map, {guard}")
    print(
        f"batched evaluation: {args.maps} maps in {batched_s:.2f} s "
        f"= {args.maps / batched_s:,.0f} maps/s (target: 4096 maps ≤ 5 s), "
        f"accuracy {batched.accuracy:.3f}"
    )
    print(f"per-map loop:       {loop} maps in {loop_s:.2f} s = {loop / loop_s:,.0f} maps/s")
    print(f"speed-up batched / per-map: {(args.maps / batched_s) / (loop / loop_s):.1f}×")
    print(f"SRD epoch over {args.maps} maps, one SGD step each, 1 thread:")
    print(f"  autograd (today's path): {today_s:6.2f} s = {1e3 * today_s / args.maps:.3f} ms/step")
    print(f"  fused:                   {fused_s:6.2f} s = {1e3 * fused_s / args.maps:.3f} ms/step")
    print(f"  ratio autograd / fused:  {today_s / fused_s:.1f}× (targets: ≤ 3 s and ≥ 10×)")
    moved = (today[-1] - build_model(project, args.preset).kernel_stack().detach()).abs().max()
    steps = [*[c for c in CHECKPOINTS if c < args.maps], args.maps]
    differences = ", ".join(
        f"{s}: {(a - b).abs().max().item():.1e}"
        for s, a, b in zip(steps, today, fused, strict=True)
    )
    print(f"  max |weight difference| after steps {differences} (weights moved {moved:.2f})")


if __name__ == "__main__":
    main()
