"""The appendix's design stages 0–4: how HalfCheetahSRD was built, one test at a time.

0. open-loop thigh swings (the devtest that showed the gait);
1. zero control: the pose the cheetah rests in, the stable pose p of xS and zS;
2. the stable-pose neurons while the front thigh swings away from rest;
3. the designed FC layer on xS, zS and their inverses;
4. stage 3 plus the BS (backswing) neuron.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from agents.cheetah_net import (
    ACTUATORS,
    BODIES,
    STABLE_POSE_X,
    STABLE_POSE_Z,
    HalfCheetahSRD,
    StablePoseNeuron,
    nominal_fc_weight,
)
from sim.cheetah.config import run_result
from sim.cheetah.engine import Controller, HalfCheetahBatch, drive
from sim.cheetah.plots import plot_lines, plot_rest_pose
from sim.cheetah.world import (
    CONTROL_INTERVAL,
    DESIGN_START_X,
    WARMUP_STEPS,
    evaluation_steps,
    relative_pose,
)
from sim.configs import (
    DESIGN_STEPS,
    DEVTEST_STEPS,
    STAGE0_STRENGTHS,
    STAGE2_SWING_FROM,
    STAGE2_WINDOW,
    CheetahConfig,
)
from sim.experiment import ProgressFn, Stopwatch, write_json

STAGE0_PATTERN_END = 150
"""Stage 0 writes its swing pattern once, up to this step; the last control then stays."""

_BACK_THIGH, _FRONT_THIGH = ACTUATORS.index("bt"), ACTUATORS.index("ft")


def _stage_steps(config: CheetahConfig, default: int) -> int:
    return config.steps or default


def _constant_controller(control: np.ndarray) -> Controller:
    def controller(t: int, positions: np.ndarray) -> np.ndarray:
        return control

    return controller


_NO_NETWORK = {"backswing": None, "inhibitor": None, "srd": "off"}


def run_stage0(config: CheetahConfig, out_dir: Path, progress: ProgressFn) -> dict[str, Any]:
    """Open-loop devtest: front thigh −2s for 25 steps, then back thigh −s for 25 steps.

    As the reference devtest, the pattern is written once (t = 100 … 149, the last control then
    stays latched) for each strength s; one more trial repeats [0,0,0,−1,0,0] / [−1,0,0,0,0,0]
    cyclically from t = 101 (the reference's "simple example").
    """
    watch = Stopwatch()
    steps = _stage_steps(config, DEVTEST_STEPS)
    strengths = np.array(STAGE0_STRENGTHS)
    n = len(strengths) + 1
    front, back = np.zeros((n, len(ACTUATORS))), np.zeros((n, len(ACTUATORS)))
    front[:-1, _FRONT_THIGH], back[:-1, _BACK_THIGH] = -2 * strengths, -strengths
    front[-1, _FRONT_THIGH], back[-1, _BACK_THIGH] = -1.0, -1.0
    control = np.zeros((n, len(ACTUATORS)))
    first_switch = WARMUP_STEPS + CONTROL_INTERVAL
    switch_steps = [WARMUP_STEPS, WARMUP_STEPS + 1, *range(first_switch, steps, CONTROL_INTERVAL)]

    def controller(t: int, positions: np.ndarray) -> np.ndarray:
        pattern = front if t % (2 * CONTROL_INTERVAL) < CONTROL_INTERVAL else back
        if t < STAGE0_PATTERN_END:
            control[:-1] = pattern[:-1]
        if t > WARMUP_STEPS:
            control[-1] = pattern[-1]
        return control.copy()

    with HalfCheetahBatch(n, start_x=DESIGN_START_X, threads=config.threads) as batch:
        traj = drive(batch, steps, switch_steps, controller, progress=progress)
        timestep = batch.timestep
    displacement = traj.torso_x - traj.torso_x[:, :1]
    labels = [f"s={s:g} once" for s in strengths] + ["cyclic ±1"]
    figure = plot_lines(
        out_dir / "stage0_torso_x.png",
        np.arange(steps) * timestep,
        [(label, traj.torso_x[i]) for i, label in enumerate(labels)],
        title="Stage 0: open-loop thigh swings (torso x)",
        ylabel="torso x (m)",
    )
    swings = [(float(s), "once") for s in strengths] + [(1.0, "cyclic")]
    runs = [  # no network: no backswing or inhibitor; the grid's keys kept for its readers
        {
            "strength": s,
            "pattern": pattern,
            **_NO_NETWORK,
            "trial": i + 1,
            "final_displacement": float(displacement[i, -1]),
        }
        for i, (s, pattern) in enumerate(swings)
    ]
    return _stage_result(config, 0, steps, runs, [figure.name], watch)


def run_stage1(config: CheetahConfig, out_dir: Path, progress: ProgressFn) -> dict[str, Any]:
    """Zero control: the cheetah drops and rests; its last pose is the stable pose p."""
    watch = Stopwatch()
    steps = _stage_steps(config, DESIGN_STEPS)
    with HalfCheetahBatch(1, start_x=DESIGN_START_X, threads=1) as batch:
        traj = drive(
            batch, steps, [], _constant_controller(np.zeros((1, len(ACTUATORS)))), record_poses=True
        )
    assert traj.poses is not None
    u = relative_pose(traj.poses[0, -1])
    pose = {"x_rel": u[:6].tolist(), "z_rel": u[6:].tolist(), "bodies": list(BODIES[1:])}
    designed = np.array(STABLE_POSE_X + STABLE_POSE_Z)
    difference = float(np.abs(u - designed).max())
    write_json(out_dir / "stable_pose.json", pose)
    figure = plot_rest_pose(out_dir / "stage1_pose.png", traj.poses[0, -1])
    result = _stage_result(config, 1, steps, [], ["stable_pose.json", figure.name], watch)
    result |= {"stable_pose": pose, "max_abs_difference_to_designed_pose": difference}
    return result


def run_stage2(config: CheetahConfig, out_dir: Path, progress: ProgressFn) -> dict[str, Any]:
    """Rest until t = 250, then swing the front thigh forward: xS, zS fall, inverses rise."""
    watch = Stopwatch()
    steps = _stage_steps(config, DESIGN_STEPS)
    swing = np.zeros((1, len(ACTUATORS)))
    swing[0, _FRONT_THIGH] = -1.0
    with HalfCheetahBatch(1, start_x=DESIGN_START_X, threads=1) as batch:
        traj = drive(
            batch, steps, [STAGE2_SWING_FROM], _constant_controller(swing), record_poses=True
        )
        timestep = batch.timestep
    assert traj.poses is not None
    u = torch.from_numpy(relative_pose(traj.poses[0])).to(torch.float32)
    x_neuron = StablePoseNeuron(torch.tensor([STABLE_POSE_X]).expand(steps, -1))
    z_neuron = StablePoseNeuron(torch.tensor([STABLE_POSE_Z]).expand(steps, -1))
    with torch.no_grad():
        x_stable = x_neuron(u[:, :6]).numpy()
        z_stable = z_neuron(u[:, 6:]).numpy()
    figure = plot_lines(
        out_dir / "stage2_stable_pose.png",
        np.arange(steps) * timestep,
        [("xS", x_stable), ("zS", z_stable), ("xS_inv", 1 - x_stable), ("zS_inv", 1 - z_stable)],
        title=f"Stage 2: stable-pose neurons (front thigh swings from t = {STAGE2_SWING_FROM})",
        ylabel="activation",
    )
    before = slice(STAGE2_SWING_FROM - STAGE2_WINDOW, STAGE2_SWING_FROM)
    after = slice(min(STAGE2_SWING_FROM + STAGE2_WINDOW, steps - 1), steps)
    result = _stage_result(config, 2, steps, [], [figure.name], watch)
    result["activations"] = {
        "xS_before_swing": float(x_stable[before].mean()),
        "zS_before_swing": float(z_stable[before].mean()),
        "xS_after_swing": float(x_stable[after].mean()),
        "zS_after_swing": float(z_stable[after].mean()),
    }
    return result


def run_design_network(
    config: CheetahConfig, out_dir: Path, progress: ProgressFn, stage: int
) -> dict[str, Any]:
    """Stages 3 and 4: the designed FC (+1e-4 on every weight), no inhibitor, no SRD.

    Stage 3 has no BS neuron (backswing 0); stage 4 adds it for each configured backswing
    (5 when the grid default is left unchanged, as in the appendix).
    """
    watch = Stopwatch()
    steps = _stage_steps(config, DESIGN_STEPS)
    backswings = config.stage_backswings()
    n = len(backswings)
    weight = nominal_fc_weight(design_offset=True).expand(n, -1, -1)
    net = HalfCheetahSRD(
        torch.tensor(backswings, dtype=torch.float32), fc_weight=weight, inhibitor_path=False
    )
    zero = torch.zeros(n)

    def controller(t: int, positions: np.ndarray) -> np.ndarray:
        u = torch.from_numpy(relative_pose(positions)).to(torch.float32)
        actions, _ = net.act(u, zero)
        return actions.to(torch.float64).numpy()

    with HalfCheetahBatch(n, start_x=DESIGN_START_X, threads=config.threads) as batch:
        traj = drive(
            batch, steps, evaluation_steps(steps), controller, record_poses=True, progress=progress
        )
        timestep = batch.timestep
    assert traj.poses is not None
    labels = ["no BS neuron"] if stage == 3 else [f"backswing {b:g}" for b in backswings]
    figure = plot_lines(
        out_dir / f"stage{stage}_torso.png",
        np.arange(steps) * timestep,
        [(label, traj.poses[i, :, 0, 0]) for i, label in enumerate(labels)],
        title=f"Stage {stage}: designed network, torso position",
        ylabel="torso x (m)",
        extra=[(label, traj.poses[i, :, 0, 2]) for i, label in enumerate(labels)],
        extra_ylabel="torso z (m)",
    )
    displacement = traj.torso_x[:, -1] - traj.torso_x[:, 0]
    runs = [  # the grid's keys: no inhibitor path, no SRD, one trial per backswing
        {"backswing": b, "inhibitor": 0, "srd": "off", "trial": 1, "final_displacement": float(d)}
        for b, d in zip(backswings, displacement, strict=True)
    ]
    return _stage_result(config, stage, steps, runs, [figure.name], watch)


def _stage_result(
    config: CheetahConfig,
    stage: int,
    steps: int,
    runs: list[dict[str, Any]],
    artifacts: list[str],
    watch: Stopwatch,
) -> dict[str, Any]:
    return run_result(config, {"stage": stage, "steps": steps, "runs": runs}, artifacts, watch)


STAGES: dict[int, Callable[[CheetahConfig, Path, ProgressFn], dict[str, Any]]] = {
    0: run_stage0,
    1: run_stage1,
    2: run_stage2,
    3: lambda c, o, p: run_design_network(c, o, p, 3),
    4: lambda c, o, p: run_design_network(c, o, p, 4),
}
"""Design stage → its runner."""
