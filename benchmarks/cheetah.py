"""Speed of the batched half-cheetah grid against bare MuJoCo, in one run.

Prints:
* bare ``mj_step`` throughput on one core: the grid's own control sequences replayed open-loop,
  trial after trial, with ``mj_step(model, data, 25)`` (no network, no Python per step);
* the grid engine's throughput (threaded rollout + batched network + SRD) and its ratio to the
  bare figure per core used (target ≥ 0.6), in wall time and in CPU time (the CPU-time ratio
  does not depend on how much of the cores other jobs take);
* the wall time of the full grid, 140 trials × 3600 steps (target ≤ 15 s; the reference, one
  trial at a time with the network in a Python loop, needs ~66 s);
* the per-trial Python loop (the reference's structure) on a few trials, extrapolated to 140.

Run: ``.venv/bin/python benchmarks/cheetah.py [--threads 2]``. Numbers are noisy when other
jobs share the machine.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any, ClassVar

import mujoco
import numpy as np
import torch

from agents.cheetah_net import HalfCheetahSRD
from sim.cheetah import experiment
from sim.cheetah.config import CheetahConfig
from sim.cheetah.engine import HalfCheetahBatch
from sim.cheetah.world import (
    CONTROL_INTERVAL,
    WARMUP_STEPS,
    build_model,
    inhibitor_active,
    relative_pose,
)

torch.set_num_threads(1)


class RecordingBatch(HalfCheetahBatch):
    """The engine's batches (one per unit of the grid), also remembering every chunk's
    controls for the replay."""

    batches: ClassVar[list[list[tuple[np.ndarray, int]]]] = []

    cpu_span: ClassVar[list[float]] = []

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.chunks: list[tuple[np.ndarray, int]] = []
        RecordingBatch.batches.append(self.chunks)

    def advance(self, control: np.ndarray, nstep: int) -> np.ndarray:
        self.chunks.append((np.array(control, dtype=np.float64), nstep))
        if not RecordingBatch.cpu_span:
            RecordingBatch.cpu_span.append(time.process_time())
        positions = super().advance(control, nstep)
        RecordingBatch.cpu_span[1:] = [time.process_time()]
        return positions


def bare_replay(batches: list[list[tuple[np.ndarray, int]]]) -> tuple[float, float, int]:
    """Single-thread mj_step over the recorded controls, trial by trial: (wall s, CPU s, steps)."""
    model = build_model()
    steps = 0
    start, cpu = time.perf_counter(), time.process_time()
    for chunks in batches:
        for trial in range(len(chunks[0][0]) if chunks else 0):
            data = mujoco.MjData(model)
            for control, nstep in chunks:
                data.ctrl[:] = control[trial]
                mujoco.mj_step(model, data, nstep)
                steps += nstep
    return time.perf_counter() - start, time.process_time() - cpu, steps


def python_loop(trials: int, steps: int) -> float:
    """The reference's structure: one trial at a time, mj_step and the network in Python."""
    model = build_model()
    start = time.perf_counter()
    for _ in range(trials):
        data = mujoco.MjData(model)
        net = HalfCheetahSRD(torch.tensor([3.0]))
        for t in range(steps):
            mujoco.mj_step(model, data)
            pose = data.xpos[1:].copy()
            if t > WARMUP_STEPS and (t - WARMUP_STEPS - 1) % CONTROL_INTERVAL == 0:
                u = torch.from_numpy(relative_pose(pose)[None]).to(torch.float32)
                inhibitor = torch.tensor([2.0 * inhibitor_active(t)])
                actions, _ = net.act(
                    u, inhibitor, srd=torch.tensor([True]), lr=torch.tensor([1e-4])
                )
                data.ctrl[:] = actions[0].to(torch.float64).numpy()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--loop-trials", type=int, default=4)
    args = parser.parse_args()

    config = CheetahConfig(threads=args.threads, video=False)
    experiment.HalfCheetahBatch = RecordingBatch  # type: ignore[misc]
    try:
        with tempfile.TemporaryDirectory() as out:
            start = time.perf_counter()
            result = experiment.run(config, out_dir=Path(out))
            wall = time.perf_counter() - start
    finally:
        experiment.HalfCheetahBatch = HalfCheetahBatch  # type: ignore[misc]
    n, steps = result["n_runs"], result["steps"]
    engine_rate = n * steps / result["simulation_s"]
    # CPU seconds of the whole process (rollout threads + network + SRD) while the grid ran
    engine_cpu = RecordingBatch.cpu_span[-1] - RecordingBatch.cpu_span[0]
    bare_s, bare_cpu, bare_steps = bare_replay(RecordingBatch.batches)
    bare_rate = bare_steps / bare_s
    loop_s = python_loop(args.loop_trials, steps)

    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"grid: {n} trials x {steps} steps = {n * steps} steps, threads {args.threads}")
    print(f"machine load average (1, 5, 15 min)  : {load}  (other jobs make wall times noisy)")
    print(f"bare mj_step, 1 core, same controls : {bare_rate:10.0f} steps/s")
    print(f"grid engine (rollout + network + SRD): {engine_rate:10.0f} steps/s")
    per_core = engine_rate / (args.threads * bare_rate)
    print(f"engine per core / bare single core   : {per_core:10.2f}   (target >= 0.60, wall)")
    cpu_ratio = (bare_cpu / bare_steps) / (engine_cpu / (n * steps))
    print(f"same ratio in CPU time (load-proof)  : {cpu_ratio:10.2f}   (engine CPU incl. network)")
    print(f"grid simulation wall time            : {result['simulation_s']:10.2f} s")
    print(f"grid wall time incl. artifacts       : {wall:10.2f} s   (target <= 15 s)")
    per_trial = loop_s / args.loop_trials
    print(
        f"per-trial Python loop (reference way): {steps / per_trial:10.0f} steps/s, "
        f"{per_trial * n:.1f} s for {n} trials (measured on {args.loop_trials})"
    )
    print(f"speed-up of the grid engine over it  : {per_trial * n / wall:10.1f} x")


if __name__ == "__main__":
    main()
