"""MuJoCo half-cheetah driven by HalfCheetahSRD: the whole experiment grid in one batch.

The model is Gymnasium's ``half_cheetah.xml`` with the reference's four edits (spec cheetah.md
§1): the torso starts at x = −2 (−1 in the design stages), the floor lies at z = −0.5 (so the
cheetah drops ~0.5 m and settles), the floor is drawn 15 m wide and its checker is grey. Seven
position sensors report the body origins (``xpos``) so the batched rollout hands back the pose
of every step; they do not touch the physics.

Loop conventions (spec §2, §9), per trial and iteration t = 0, 1, …, steps − 1:
1. ``mj_step`` with the current control;
2. read the body positions — the kinematics of the state *before* this step's integration, so
   the control reacts to the pose with a one-step (10 ms) delay;
3. log the torso x;
4. for t ≤ 100 the control stays zero (the cheetah lands); at t = 101 + 25k the network is
   evaluated on the pose just read, the result is applied from step t + 1 and held 25 steps;
   the inhibitor of a run is on when t > 500 and t mod 1000 < 600.

All trials advance together: MuJoCo's native rollout steps every trial's MjData in parallel
threads for one 25-step chunk, then one batched network evaluation (with the SRD updates of the
trials that learn) produces the next chunk's controls.
"""

from __future__ import annotations

import importlib.resources
import itertools
import math
import os
import subprocess
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import mujoco
import numpy as np
import torch
from mujoco import rollout
from pydantic import Field

from agents.cheetah_net import (
    ACTUATORS,
    BODIES,
    STABLE_POSE_X,
    STABLE_POSE_Z,
    HalfCheetahSRD,
    StablePoseNeuron,
    noisy_fc_weight,
    nominal_fc_weight,
)
from sim.experiment import ProgressFn, Stopwatch, config_dict, no_progress, write_json

START_X = -2.0
"""Torso start x in the main experiment (Gymnasium: 0)."""
DESIGN_START_X = -1.0
"""Torso start x in the design stages 0–4."""
FLOOR_Z = -0.5
"""Floor height (Gymnasium: 0): the cheetah starts ~0.5 m higher and drops onto it."""
FLOOR_SIZE = 15.0
"""Drawn floor half-size (planes collide everywhere; rendering only)."""
CHECKER_GREY = 0.4
"""First checker colour of the floor texture (Gymnasium: black; cosmetic)."""

WARMUP_STEPS = 100
"""Zero control for t ≤ WARMUP_STEPS: the cheetah lands and settles."""
CONTROL_INTERVAL = 25
"""Steps a computed control is held before the network runs again (the reference's momentum)."""
INHIBITOR_FROM = 500
"""The inhibitor schedule starts after this step ..."""
INHIBITOR_PERIOD = 1000
"""... and in every period of this many steps ..."""
INHIBITOR_WINDOW = 600
"""... it is on for the first this many steps."""

MAIN_STEPS = 3600
"""36 s trials of the main experiment."""
DESIGN_STEPS = 1200
"""12 s runs of the design stages 1–4."""
DEVTEST_STEPS = 400
"""4 s runs of design stage 0."""
STAGE0_STRENGTHS = (-2.0, -1.0, -0.5, 0.25, 0.5, 0.75, 1.0, 2.0, 3.0)
"""Actuator strengths s tried by the stage-0 devtest."""
STAGE2_SWING_FROM = 250
"""Stage 2: the front thigh is swung forward from this step on."""
STAGE4_DEFAULT_BACKSWING = 5.0
"""Stage 4 uses this backswing when the grid's default is left unchanged."""
VIDEO_FPS = 10
"""Frames per simulated second of the GIF (the reference filmed at 15)."""
VIDEO_SECONDS = 14.0
"""Length of the GIF: running, the short stall at 5 s and the first long stop at 10 s."""
FIGURE_DPI = 80
"""Keeps the figures small."""
PLOT_STRIDE = 5
"""Plot every 5th step (0.05 s): the curves look the same and draw faster."""
CSV_STRIDE = 10
"""displacement.csv keeps every 10th step (0.1 s)."""

PROGRESS_REPORTS = 40
"""Progress reports per drive."""
GL_BACKENDS = ("egl", "osmesa", "glfw")
"""Offscreen OpenGL back ends tried, in order, for the GIF."""

_FULL_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
_CONTROL_SPEC = mujoco.mjtState.mjSTATE_CTRL.value


# ---------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------
def half_cheetah_xml() -> Path:
    """Path of Gymnasium's ``half_cheetah.xml`` (raises naming ``pip install gymnasium``)."""
    try:
        root = importlib.resources.files("gymnasium")
    except ModuleNotFoundError as exc:
        raise ModuleNotFoundError(
            "the half-cheetah model comes from Gymnasium: pip install gymnasium"
        ) from exc
    path = Path(str(root / "envs" / "mujoco" / "assets" / "half_cheetah.xml"))
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} is missing: reinstall Gymnasium with MuJoCo assets (pip install gymnasium)"
        )
    return path


def build_model(start_x: float = START_X) -> mujoco.MjModel:
    """Gymnasium's half-cheetah with the reference's edits and one position sensor per body."""
    spec = mujoco.MjSpec.from_file(str(half_cheetah_xml()))
    spec.body("torso").pos = [start_x, 0.0, 0.7]
    floor = spec.geom("floor")
    floor.pos = [0.0, 0.0, FLOOR_Z]
    floor.size = [FLOOR_SIZE, FLOOR_SIZE, FLOOR_SIZE]
    spec.texture("texplane").rgb1 = [CHECKER_GREY] * 3
    for body in BODIES:
        spec.add_sensor(
            name=f"origin_{body}",
            type=mujoco.mjtSensor.mjSENS_FRAMEPOS,
            objtype=mujoco.mjtObj.mjOBJ_XBODY,
            objname=body,
        )
    with warnings.catch_warnings():
        # The model's settotalmass=14 is deprecated but still exact; keep the model as shipped.
        warnings.filterwarnings("ignore", message=".*settotalmass.*")
        return spec.compile()


def relative_pose(positions: np.ndarray) -> np.ndarray:
    """Network input u (…, 12): x then z of bthigh..ffoot minus the torso's, from (…, 7, 3)."""
    rel = positions[..., 1:, :] - positions[..., :1, :]
    return np.concatenate([rel[..., 0], rel[..., 2]], axis=-1)


class HalfCheetahBatch:
    """``n`` independent half-cheetahs stepped together by MuJoCo's threaded rollout.

    Observation: the world positions (n, 7, 3) of the body origins torso, bthigh, bshin, bfoot,
    fthigh, fshin, ffoot after every ``mj_step`` (the pose the step started from).
    Action: torques in [−1, 1] for bt, bs, bf, ft, fs, ff (gears 120, 90, 60, 120, 60, 30),
    held for the whole chunk. No reward, no termination, no reset noise: ``reset`` puts every
    trial at qpos = qvel = 0 (torso at ``start_x``, z = 0.7). One step is 0.01 s.

    Args:
        n: number of trials.
        start_x: torso start x.
        threads: worker threads of the rollout pool (1 = the calling thread).
    """

    def __init__(self, n: int, *, start_x: float = START_X, threads: int = 2) -> None:
        self.model = build_model(start_x)
        self.n = n
        self.timestep = float(self.model.opt.timestep)
        self._qvel = slice(1 + self.model.nq, 1 + self.model.nq + self.model.nv)
        nthread = threads if threads > 1 else 0
        self._pool: rollout.Rollout | None = rollout.Rollout(nthread=nthread)
        self._data = [mujoco.MjData(self.model) for _ in range(max(nthread, 1))]
        self._models = [self.model] * n
        self.chunk_qpos = np.empty((n, 0, self.model.nq))
        """Joint positions after each step of the last chunk (n, nstep, nq)."""
        self.reset()

    def reset(self) -> None:
        """All trials back to the initial state (qpos = qvel = 0, time 0)."""
        data = mujoco.MjData(self.model)
        size = mujoco.mj_stateSize(self.model, _FULL_STATE)
        one = np.empty(size)
        mujoco.mj_getState(self.model, data, one, _FULL_STATE)
        self.state = np.ascontiguousarray(np.broadcast_to(one, (self.n, size)))
        self.warmstart = np.zeros((self.n, self.model.nv))

    def advance(self, control: np.ndarray, nstep: int) -> np.ndarray:
        """Step every trial ``nstep`` times under ``control`` (n, 6); positions (n, nstep, 7, 3)."""
        if self._pool is None:
            raise RuntimeError("HalfCheetahBatch is closed")
        controls = np.ascontiguousarray(
            np.broadcast_to(np.asarray(control, dtype=np.float64)[:, None, :], (self.n, nstep, 6))
        )
        states = np.empty((self.n, nstep, self.state.shape[1]))
        sensors = np.empty((self.n, nstep, self.model.nsensordata))
        previous_qvel = self.state[:, self._qvel].copy()
        self._pool.rollout(
            self._models,
            self._data,
            initial_state=self.state,
            control=controls,
            initial_warmstart=self.warmstart,
            skip_checks=True,
            nstep=nstep,
            state=states,
            sensordata=sensors,
        )
        self.state = np.ascontiguousarray(states[:, -1])
        self.chunk_qpos = states[:, :, 1 : 1 + self.model.nq]
        before_last = states[:, -2, self._qvel] if nstep > 1 else previous_qvel
        # The rollout does not hand back the solver's warm start (the last step's acceleration);
        # the last step's velocity change is the closest estimate. It only seeds the constraint
        # solver: trajectories move by < 1e-9 m against an uninterrupted mj_step loop.
        self.warmstart = (self.state[:, self._qvel] - before_last) / self.timestep
        return sensors.reshape(self.n, nstep, len(BODIES), 3)

    def qpos(self) -> np.ndarray:
        """Current joint positions (n, nq)."""
        return self.state[:, 1 : 1 + self.model.nq]

    def close(self) -> None:
        """Stop the rollout threads."""
        if self._pool is not None:
            self._pool.close()
            self._pool = None

    def __enter__(self) -> HalfCheetahBatch:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------
# Schedules and the driver loop
# ---------------------------------------------------------------------------------------------
def evaluation_steps(steps: int) -> list[int]:
    """Iterations at which the network runs: t = 101 + 25k < steps."""
    return list(range(WARMUP_STEPS + 1, steps, CONTROL_INTERVAL))


def inhibitor_active(t: int) -> bool:
    """True when the run's inhibitor is on at iteration t (t > 500 and t mod 1000 < 600)."""
    return t > INHIBITOR_FROM and t % INHIBITOR_PERIOD < INHIBITOR_WINDOW


def stop_windows(steps: int) -> list[tuple[int, int]]:
    """The [first, last] iterations of each stretch of the inhibitor schedule below ``steps``."""
    windows = []
    for period in range(0, steps, INHIBITOR_PERIOD):
        first = max(period, INHIBITOR_FROM + 1)
        last = min(period + INHIBITOR_WINDOW, steps) - 1
        if first <= last:
            windows.append((first, last))
    return windows


Controller = Callable[[int, np.ndarray], np.ndarray]
"""(iteration t, body positions (n, 7, 3) read after step t) → controls (n, 6) from step t + 1."""


@dataclass
class Trajectories:
    """What a drive recorded."""

    torso_x: np.ndarray
    """(n, steps) torso x after each iteration's read (pose of the state the step started from)."""
    poses: np.ndarray | None
    """(n, steps, 7, 3) body positions of every step, when recorded."""
    qpos: np.ndarray | None
    """(steps + 1, nq) joint positions of one trial (for the video), when recorded."""


def drive(
    batch: HalfCheetahBatch,
    steps: int,
    controller_steps: Sequence[int],
    controller: Controller,
    *,
    record_poses: bool = False,
    keep_qpos_of: int | None = None,
    progress: ProgressFn = no_progress,
) -> Trajectories:
    """Run ``steps`` iterations from a reset, calling ``controller`` after each listed iteration.

    The chunk before an evaluation at iteration t ends with step t, so the controller sees
    exactly the pose a per-step loop reads after its t-th ``mj_step``; the control it returns
    is used from step t + 1 on (the one-step delay of the reference).
    """
    batch.reset()
    torso_x = np.empty((batch.n, steps))
    poses = np.empty((batch.n, steps, len(BODIES), 3)) if record_poses else None
    qpos = None
    if keep_qpos_of is not None:
        qpos = np.empty((steps + 1, batch.model.nq))
        qpos[0] = batch.qpos()[keep_qpos_of]
    control = np.zeros((batch.n, len(ACTUATORS)))
    bounds = [t for t in sorted(set(controller_steps)) if 0 <= t < steps]
    chunk_ends = [*bounds, steps - 1] if not bounds or bounds[-1] != steps - 1 else bounds
    start = 0
    for end in chunk_ends:
        if end < start:
            continue
        nstep = end - start + 1
        positions = batch.advance(control, nstep)
        torso_x[:, start : end + 1] = positions[:, :, 0, 0]
        if poses is not None:
            poses[:, start : end + 1] = positions
        if qpos is not None:
            qpos[start + 1 : end + 2] = batch.chunk_qpos[keep_qpos_of]
        if end in bounds:
            control = controller(end, positions[:, -1])
        if (end + 1) * PROGRESS_REPORTS // steps > start * PROGRESS_REPORTS // steps:
            progress((end + 1) / steps, f"step {end + 1}/{steps}")
        start = end + 1
    return Trajectories(torso_x=torso_x, poses=poses, qpos=qpos)


# ---------------------------------------------------------------------------------------------
# The experiment
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CheetahConfig:
    """HalfCheetahSRD: the grid backswing × inhibitor × SRD (× learning rate) × trial."""

    backswing: tuple[float, ...] = (1.0, 2.0, 3.0, 4.0, 5.0)
    """BS neuron gains to run (how hard the back thigh answers the pitch signal)."""
    inhibitor: tuple[Annotated[float, Field(ge=0)], ...] = (0.0, 2.0)
    """Inhibitor values of the stop command (0: never stop; 2: stop in the scheduled windows)."""
    srd: Literal["on", "off", "both"] = "both"
    """Self-reward optimisation during the trial: on, off or both (paired, same weights)."""
    trials: Annotated[int, Field(ge=1, le=1000)] = 7
    """Seeded trials per condition (weight noise differs per trial; --nominal runs one)."""
    steps: Annotated[int, Field(ge=1, le=1_000_000)] | None = None
    """Simulation steps of 0.01 s (default 3600; stages: 400 for 0, 1200 for 1–4)."""
    nominal: bool = False
    """Noise-free designed weights (deterministic, one trial per condition)."""
    stage: Annotated[int, Field(ge=0, le=4)] | None = None
    """Run one of the appendix's design stages 0–4 instead of the main grid."""
    lr: tuple[Annotated[float, Field(gt=0)], ...] = (1e-4,)
    """SGD learning rate(s) of SRD; several values sweep them (an extra grid axis)."""
    threads: Annotated[int, Field(ge=1, le=64)] = 2
    """Threads stepping MuJoCo in parallel."""
    video: bool = True
    """Render a GIF of one trial when an offscreen OpenGL context is available."""
    seed: int = 0
    """Seeds the per-trial weight noise: same seed, same numbers."""


@dataclass(frozen=True)
class Condition:
    """One cell of the grid."""

    backswing: float
    inhibitor: float
    srd: bool
    lr: float | None


def grid_conditions(config: CheetahConfig) -> list[Condition]:
    """Conditions in report order: SRD on (each lr) before off, then backswing, inhibitor."""
    variants: list[tuple[bool, float | None]] = []
    if config.srd in ("on", "both"):
        variants += [(True, lr) for lr in config.lr]
    if config.srd in ("off", "both"):
        variants.append((False, None))
    return [
        Condition(float(b), float(i), on, lr)
        for (on, lr), b, i in itertools.product(variants, config.backswing, config.inhibitor)
    ]


def trial_generator(seed: int, trial: int) -> torch.Generator:
    """The noise generator of trial ``trial``: the same draw in every condition (paired)."""
    state = np.random.SeedSequence([seed, trial]).generate_state(1, dtype=np.uint64)[0]
    return torch.Generator().manual_seed(int(state) & (2**63 - 1))


def run(
    config: CheetahConfig, *, out_dir: Path, progress: ProgressFn = no_progress
) -> dict[str, Any]:
    """Run the grid or a design stage, write its artifacts into ``out_dir``, return the result."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if config.stage is not None:
        return STAGES[config.stage](config, out_dir, progress)
    return run_grid(config, out_dir=out_dir, progress=progress)


def run_grid(
    config: CheetahConfig, *, out_dir: Path, progress: ProgressFn = no_progress
) -> dict[str, Any]:
    """The main experiment: every trial of every condition in one batch."""
    watch = Stopwatch()
    steps = config.steps or MAIN_STEPS
    trials = 1 if config.nominal else config.trials
    cells = [(c, k) for c in grid_conditions(config) for k in range(trials)]
    n = len(cells)
    backswing = torch.tensor([c.backswing for c, _ in cells], dtype=torch.float32)
    inhibitor = torch.tensor([c.inhibitor for c, _ in cells], dtype=torch.float32)
    learns = torch.tensor([c.srd for c, _ in cells])
    lr = torch.tensor([c.lr or 0.0 for c, _ in cells], dtype=torch.float32)
    if config.nominal:
        weights = None
    else:
        draws = noisy_fc_weight([trial_generator(config.seed, k) for k in range(trials)])
        weights = draws[torch.tensor([k for _, k in cells])]
    net = HalfCheetahSRD(backswing, fc_weight=weights)
    initial = [p.detach().clone() for p in net.parameters()]
    true_verdicts = torch.zeros(n)
    judged = 0
    inhibited_evals: list[int] = []

    def controller(t: int, positions: np.ndarray) -> np.ndarray:
        nonlocal judged
        u = torch.from_numpy(relative_pose(positions)).to(torch.float32)
        active = inhibitor_active(t)
        if active:
            inhibited_evals.append(t)
        actions, logits = net.act(u, inhibitor * float(active), srd=learns, lr=lr)
        if logits is not None:
            true_verdicts.add_((logits[:, 0] >= logits[:, 1]).float())
            judged += 1
        return actions.to(torch.float64).numpy()

    video_trial = _video_trial(cells)
    with HalfCheetahBatch(n, threads=config.threads) as batch:
        traj = drive(
            batch,
            steps,
            evaluation_steps(steps),
            controller,
            keep_qpos_of=video_trial if config.video else None,
            progress=lambda f, m: progress(0.95 * f, m),
        )
    simulated_s = watch.elapsed()
    displacement = traj.torso_x - traj.torso_x[:, :1]
    inhibited_steps = _held_steps(inhibited_evals, steps)
    speeds = _speeds(traj.torso_x, inhibited_steps, batch.timestep)
    controller_change, pfc_change = _parameter_changes(net, initial)
    runs = []
    for index, (cond, k) in enumerate(cells):
        runs.append(
            {
                "backswing": cond.backswing,
                "inhibitor": cond.inhibitor,
                "srd": "on" if cond.srd else "off",
                "lr": cond.lr,
                "trial": k + 1,
                "final_displacement": float(displacement[index, -1]),
                "inhibited_abs_speed": speeds["inhibited"][index],
                "free_speed": speeds["free"][index],
                "true_verdict_fraction": (
                    float(true_verdicts[index]) / judged if cond.srd and judged else None
                ),
                "controller_change": controller_change[index],
                "pfc_change": pfc_change[index],
            }
        )
    summary = summarise(runs)
    progress(0.96, "writing artifacts")
    artifacts = _write_grid_artifacts(out_dir, runs, summary, cells, displacement, net)
    figure = plot_displacement(out_dir / "displacement.png", cells, displacement, batch.timestep)
    artifacts.append(figure.name)
    if len(config.lr) > 1 and config.srd == "both":
        artifacts.append(plot_lr_sweep(out_dir / "lr_sweep.png", runs).name)
    video: dict[str, Any] = {"video": None, "video_note": "video off (--no-video)"}
    if config.video and traj.qpos is not None:
        cond, k = cells[video_trial]
        label = f"b{cond.backswing:g} i{cond.inhibitor:g} srd {'on' if cond.srd else 'off'}"
        progress(0.97, "rendering the GIF")
        video = render_gif(out_dir / "cheetah.gif", traj.qpos, START_X, f"{label} trial {k + 1}")
        if video["video"]:
            artifacts.append(video["video"])
    return {
        "config": config_dict(config),
        "trials": trials,
        "steps": steps,
        "n_runs": n,
        "runs": runs,
        "summary": summary,
        "simulated_steps": n * steps,
        "simulation_s": simulated_s,
        **video,
        "artifacts": artifacts,
        "elapsed_s": watch.elapsed(),
    }


def _video_trial(cells: list[tuple[Condition, int]]) -> int:
    """The trial to film: the first with inhibitor > 0 (it runs and stops), else the first."""
    return next((i for i, (c, _) in enumerate(cells) if c.inhibitor > 0), 0)


def _held_steps(evaluations: list[int], steps: int) -> np.ndarray:
    """Boolean (steps,) mask of the steps whose control came from the given evaluations."""
    mask = np.zeros(steps, dtype=bool)
    for t in evaluations:
        mask[t + 1 : t + 1 + CONTROL_INTERVAL] = True
    return mask


def _speeds(torso_x: np.ndarray, inhibited: np.ndarray, timestep: float) -> dict[str, list[Any]]:
    """Per trial: mean |x velocity| over the stop-command steps, mean x velocity elsewhere.

    The velocity of step t is (x[t + 1] − x[t]) / 0.01 s; "elsewhere" counts the steps after
    the first network evaluation only (the landing is not running).
    """
    velocity = np.diff(torso_x, axis=1) / timestep
    inhibited = inhibited[: velocity.shape[1]]
    free = ~inhibited
    free[: WARMUP_STEPS + 2] = False

    def mean_over(mask: np.ndarray, values: np.ndarray) -> list[float | None]:
        if not mask.any():
            return [None] * values.shape[0]
        return [float(v) for v in values[:, mask].mean(axis=1)]

    return {"inhibited": mean_over(inhibited, np.abs(velocity)), "free": mean_over(free, velocity)}


def _parameter_changes(
    net: HalfCheetahSRD, initial: list[torch.Tensor]
) -> tuple[list[float], list[float]]:
    """Largest |Δ| per trial over the controller's and over the PFC's parameters."""
    before = dict(zip((id(p) for p in net.parameters()), initial, strict=True))

    def largest(params: list[torch.Tensor]) -> list[float]:
        deltas = [(p.detach() - before[id(p)]).abs().reshape(net.n_trials, -1) for p in params]
        return torch.cat(deltas, dim=1).max(dim=1).values.tolist()

    return largest(net.controller_parameters()), largest(net.pfc_parameters())


SUMMARY_METRICS = ("final_displacement", "inhibited_abs_speed", "free_speed")
"""Per-trial numbers averaged per condition."""


def summarise(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean and (sample) SD of each metric per condition (backswing, inhibitor, srd, lr)."""
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in runs:
        groups.setdefault((r["backswing"], r["inhibitor"], r["srd"], r["lr"]), []).append(r)
    rows = []
    for (b, i, srd, lr), members in groups.items():
        row: dict[str, Any] = {"backswing": b, "inhibitor": i, "srd": srd, "lr": lr}
        row["n"] = len(members)
        for metric in SUMMARY_METRICS:
            values = np.array([m[metric] for m in members if m[metric] is not None], dtype=float)
            row[f"mean_{metric}"] = float(values.mean()) if values.size else None
            row[f"sd_{metric}"] = float(values.std(ddof=1)) if values.size > 1 else 0.0
        rows.append(row)
    return rows


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> str:
    """Rows of dicts → CSV (empty cells for None); returns the file name."""
    keys = list(rows[0]) if rows else []
    lines = [",".join(keys)]
    for row in rows:
        lines.append(",".join("" if row[k] is None else f"{row[k]}" for k in keys))
    path.write_text("\n".join(lines) + "\n")
    return path.name


def _condition_label(cond: Condition) -> str:
    srd = f"SRD on (lr {cond.lr:g})" if cond.srd else "SRD off"
    return f"{srd}, inhibitor {cond.inhibitor:g}"


def _write_grid_artifacts(
    out_dir: Path,
    runs: list[dict[str, Any]],
    summary: list[dict[str, Any]],
    cells: list[tuple[Condition, int]],
    displacement: np.ndarray,
    net: HalfCheetahSRD,
) -> list[str]:
    """runs.csv, summary.csv, displacement.csv (condition means/SD every 0.1 s), weights.json."""
    names = [_write_csv(out_dir / "runs.csv", runs), _write_csv(out_dir / "summary.csv", summary)]
    stride = CSV_STRIDE
    columns: dict[str, np.ndarray] = {"step": np.arange(0, displacement.shape[1], stride)}
    for cond, index in _condition_groups(cells).items():
        tag = f"b{cond.backswing:g}_i{cond.inhibitor:g}_" + (
            f"srd_lr{cond.lr:g}" if cond.srd else "nosrd"
        )
        values = displacement[index][:, ::stride]
        columns[f"mean_{tag}"] = values.mean(axis=0)
        columns[f"sd_{tag}"] = values.std(axis=0, ddof=1) if len(index) > 1 else 0 * values[0]
    header = ",".join(columns)
    table = np.column_stack(list(columns.values()))
    np.savetxt(
        out_dir / "displacement.csv", table, fmt="%.6g", delimiter=",", header=header, comments=""
    )
    names.append("displacement.csv")
    weights = [
        {"condition": _condition_label(c), "backswing": c.backswing, "trial": k + 1}
        | {"final_weights": net.named_weights(i)}
        for i, (c, k) in enumerate(cells)
    ]
    write_json(out_dir / "weights.json", weights)
    names.append("weights.json")
    return names


def _condition_groups(cells: list[tuple[Condition, int]]) -> dict[Condition, list[int]]:
    groups: dict[Condition, list[int]] = {}
    for i, (cond, _) in enumerate(cells):
        groups.setdefault(cond, []).append(i)
    return groups


# ---------------------------------------------------------------------------------------------
# Figures and video
# ---------------------------------------------------------------------------------------------
def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_displacement(
    path: Path, cells: list[tuple[Condition, int]], displacement: np.ndarray, timestep: float
) -> Path:
    """Mean displacement ± SD over trials against time, one line per backswing.

    Rows: SRD variants (on first, as the reference plots them), columns: inhibitor values.
    """
    plt = _pyplot()
    groups = _condition_groups(cells)
    variants = list(dict.fromkeys((c.srd, c.lr) for c in groups))
    inhibitors = list(dict.fromkeys(c.inhibitor for c in groups))
    backswings = list(dict.fromkeys(c.backswing for c in groups))
    fig, axes = plt.subplots(
        len(variants),
        len(inhibitors),
        figsize=(4.2 * len(inhibitors), 2.8 * len(variants)),
        sharex=True,
        sharey=True,
        squeeze=False,
    )
    shown = slice(None, None, PLOT_STRIDE)
    time = (np.arange(displacement.shape[1]) * timestep)[shown]
    colours = plt.get_cmap("viridis")(np.linspace(0, 0.9, len(backswings)))
    for row, (srd, lr) in enumerate(variants):
        for col, inh in enumerate(inhibitors):
            ax = axes[row][col]
            for colour, b in zip(colours, backswings, strict=True):
                index = groups[Condition(b, inh, srd, lr)]
                values = displacement[index][:, shown]
                mean = values.mean(axis=0)
                sd = values.std(axis=0, ddof=1) if len(index) > 1 else 0 * mean
                ax.plot(time, mean, color=colour, lw=1.2, label=f"backswing {b:g}")
                ax.fill_between(time, mean - sd, mean + sd, color=colour, alpha=0.2, lw=0)
            if inh > 0:
                for lo, hi in stop_windows(displacement.shape[1]):
                    ax.axvspan(lo * timestep, hi * timestep, color="0.85", zorder=0)
            ax.set_title(_condition_label(Condition(0, inh, srd, lr)), fontsize=9)
            ax.grid(alpha=0.3)
            if row == len(variants) - 1:
                ax.set_xlabel("time (s)")
            if col == 0:
                ax.set_ylabel("x displacement (m)")
    axes[0][0].legend(fontsize=7, loc="upper left")
    n_trials = max(len(v) for v in groups.values())
    fig.suptitle(
        f"HalfCheetahSRD: mean torso x displacement ± SD over {n_trials} trial(s)"
        " (grey: stop command)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=FIGURE_DPI)
    plt.close(fig)
    return path


def plot_lr_sweep(path: Path, runs: list[dict[str, Any]]) -> Path:
    """SRD's effect against its learning rate, paired with the SRD-off twin of each trial.

    Left: standing still under the stop command (mean |x velocity| in the stop windows,
    inhibitor > 0). Right: running (mean x velocity outside the windows, inhibitor 0).
    Points: mean over trials and backswings of (SRD on − SRD off), bars: ± SD.
    """
    plt = _pyplot()
    off = {(r["backswing"], r["inhibitor"], r["trial"]): r for r in runs if r["srd"] == "off"}
    lrs = sorted({r["lr"] for r in runs if r["srd"] == "on"})
    panels = (
        ("inhibited_abs_speed", lambda i: i > 0, "stop windows: Δ mean |vx| (m/s)"),
        ("free_speed", lambda i: i == 0, "running: Δ mean vx (m/s)"),
    )
    fig, axes = plt.subplots(1, 2, figsize=(8.4, 3.0))
    for ax, (metric, pick, title) in zip(axes, panels, strict=True):
        baseline = [r[metric] for r in off.values() if pick(r["inhibitor"]) and r[metric]]
        if baseline:
            title += f"\nSRD off: {np.mean(baseline):.3f} ± {np.std(baseline, ddof=1):.3f}"
        means, sds = [], []
        for lr in lrs:
            diffs = [
                r[metric] - off[(r["backswing"], r["inhibitor"], r["trial"])][metric]
                for r in runs
                if r["srd"] == "on" and r["lr"] == lr and pick(r["inhibitor"])
                if r[metric] is not None
            ]
            means.append(float(np.mean(diffs)) if diffs else math.nan)
            sds.append(float(np.std(diffs, ddof=1)) if len(diffs) > 1 else 0.0)
        ax.errorbar(lrs, means, yerr=sds, marker="o", capsize=3)
        ax.axhline(0.0, color="0.5", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel("SRD learning rate")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle("SRD on minus SRD off, same initial weights (mean ± SD over trials)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=FIGURE_DPI)
    plt.close(fig)
    return path


def _plot_lines(
    path: Path,
    time: np.ndarray,
    series: list[tuple[str, np.ndarray]],
    *,
    title: str,
    ylabel: str,
    extra: list[tuple[str, np.ndarray]] | None = None,
    extra_ylabel: str = "",
) -> Path:
    """One or two stacked panels of labelled lines against time."""
    plt = _pyplot()
    panels = [(series, ylabel)] + ([(extra, extra_ylabel)] if extra else [])
    fig, axes = plt.subplots(len(panels), 1, figsize=(7.0, 2.6 * len(panels)), squeeze=False)
    for ax, (lines, label) in zip(axes[:, 0], panels, strict=True):
        for name, values in lines:
            ax.plot(time, values, lw=1.1, label=name)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=3)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=FIGURE_DPI)
    plt.close(fig)
    return path


def render_gif(path: Path, qpos: np.ndarray, start_x: float, caption: str) -> dict[str, Any]:
    """Render ``qpos`` frames to a GIF in a child process with an offscreen GL back end.

    MuJoCo picks its OpenGL back end when it is imported, so each back end is tried in a fresh
    interpreter. Never raises: without a working back end the result says why.
    """
    seconds = min(VIDEO_SECONDS, (len(qpos) - 1) / 100)
    frames = np.unique(np.ceil(np.arange(0, seconds, 1 / VIDEO_FPS) * 100).astype(int))
    source = path.with_suffix(".npz")
    np.savez(source, qpos=qpos[frames], start_x=np.array(start_x))
    reasons = []
    try:
        for backend in GL_BACKENDS:
            done = subprocess.run(
                [sys.executable, "-m", "sim.cheetah", "render", str(source), str(path), caption],
                env=_child_env(backend),
                capture_output=True,
                text=True,
                timeout=300,
                check=False,
            )
            if done.returncode == 0 and path.is_file():
                return {"video": path.name, "video_note": f"rendered with MUJOCO_GL={backend}"}
            last = (done.stderr.strip().splitlines() or ["no output"])[-1]
            reasons.append(f"{backend}: {last}")
    except (OSError, subprocess.SubprocessError) as exc:
        reasons.append(str(exc))
    finally:
        source.unlink(missing_ok=True)
    return {"video": None, "video_note": "no offscreen OpenGL context: " + "; ".join(reasons)}


def _child_env(backend: str) -> dict[str, str]:
    """The current environment with MUJOCO_GL (and PyOpenGL's platform) set to ``backend``."""
    env = dict(os.environ)
    env["MUJOCO_GL"] = backend
    if backend in ("egl", "osmesa"):
        env["PYOPENGL_PLATFORM"] = backend
    project_root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [project_root, env.get("PYTHONPATH")]))
    return env


def _render_main(source: Path, target: Path, caption: str) -> None:
    """Child-process entry: draw every stored frame from the tracking camera, save a GIF."""
    from PIL import Image, ImageDraw

    stored = np.load(source)
    model = build_model(float(stored["start_x"]))
    data = mujoco.MjData(model)
    images = []
    with mujoco.Renderer(model, height=192, width=256) as renderer:
        for frame, q in enumerate(stored["qpos"]):
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera="track")
            # Software GL draws shadows and floor reflections slowly; the gait reads without.
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
            image = Image.fromarray(renderer.render())
            ImageDraw.Draw(image).text(
                (4, 4), f"{caption}  t={frame / VIDEO_FPS:4.1f}s", fill=(0, 0, 0)
            )
            images.append(image.convert("P", palette=Image.Palette.ADAPTIVE, colors=64))
    images[0].save(
        target, save_all=True, append_images=images[1:], duration=int(1000 / VIDEO_FPS), loop=0
    )


# ---------------------------------------------------------------------------------------------
# Design stages (appendix; spec §3–§6)
# ---------------------------------------------------------------------------------------------
def _stage_steps(config: CheetahConfig, default: int) -> int:
    return config.steps or default


def _constant_controller(control: np.ndarray) -> Controller:
    def controller(t: int, positions: np.ndarray) -> np.ndarray:
        return control

    return controller


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
    front, back = np.zeros((n, 6)), np.zeros((n, 6))
    front[:-1, 3], back[:-1, 0] = -2 * strengths, -strengths
    front[-1, 3], back[-1, 0] = -1.0, -1.0
    control = np.zeros((n, 6))
    switch_steps = [WARMUP_STEPS, WARMUP_STEPS + 1, *range(125, steps, CONTROL_INTERVAL)]

    def controller(t: int, positions: np.ndarray) -> np.ndarray:
        pattern = front if t % 50 < CONTROL_INTERVAL else back
        if t < 150:
            control[:-1] = pattern[:-1]
        if t > WARMUP_STEPS:
            control[-1] = pattern[-1]
        return control.copy()

    with HalfCheetahBatch(n, start_x=DESIGN_START_X, threads=config.threads) as batch:
        traj = drive(batch, steps, switch_steps, controller, progress=progress)
        timestep = batch.timestep
    displacement = traj.torso_x - traj.torso_x[:, :1]
    labels = [f"s={s:g} once" for s in strengths] + ["cyclic ±1"]
    figure = _plot_lines(
        out_dir / "stage0_torso_x.png",
        np.arange(steps) * timestep,
        [(label, traj.torso_x[i]) for i, label in enumerate(labels)],
        title="Stage 0: open-loop thigh swings (torso x)",
        ylabel="torso x (m)",
    )
    runs = [
        {"strength": float(s), "pattern": "once", "final_displacement": float(displacement[i, -1])}
        for i, s in enumerate(strengths)
    ]
    runs.append(
        {"strength": 1.0, "pattern": "cyclic", "final_displacement": float(displacement[-1, -1])}
    )
    return _stage_result(config, 0, steps, runs, [figure.name], watch)


def run_stage1(config: CheetahConfig, out_dir: Path, progress: ProgressFn) -> dict[str, Any]:
    """Zero control: the cheetah drops and rests; its last pose is the stable pose p."""
    watch = Stopwatch()
    steps = _stage_steps(config, DESIGN_STEPS)
    with HalfCheetahBatch(1, start_x=DESIGN_START_X, threads=1) as batch:
        traj = drive(batch, steps, [], _constant_controller(np.zeros((1, 6))), record_poses=True)
    assert traj.poses is not None
    u = relative_pose(traj.poses[0, -1])
    pose = {"x_rel": u[:6].tolist(), "z_rel": u[6:].tolist(), "bodies": list(BODIES[1:])}
    designed = np.array(STABLE_POSE_X + STABLE_POSE_Z)
    difference = float(np.abs(u - designed).max())
    write_json(out_dir / "stable_pose.json", pose)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.0, 3.0))
    rest = traj.poses[0, -1]
    ax.plot(rest[:4, 0], rest[:4, 2], "o-", label="torso → back leg")
    ax.plot(rest[[0, 4, 5, 6], 0], rest[[0, 4, 5, 6], 2], "o-", label="torso → front leg")
    for i, (x, z) in enumerate(rest[:, [0, 2]]):
        ax.annotate(f"{i}", (x, z), textcoords="offset points", xytext=(3, 3), fontsize=8)
    ax.axhline(FLOOR_Z, color="0.5", lw=0.8)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title("Stage 1: resting pose (0 torso … 6 front foot)", fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "stage1_pose.png", dpi=FIGURE_DPI)
    plt.close(fig)
    result = _stage_result(config, 1, steps, [], ["stable_pose.json", "stage1_pose.png"], watch)
    result |= {"stable_pose": pose, "max_abs_difference_to_designed_pose": difference}
    return result


def run_stage2(config: CheetahConfig, out_dir: Path, progress: ProgressFn) -> dict[str, Any]:
    """Rest until t = 250, then swing the front thigh forward: xS, zS fall, inverses rise."""
    watch = Stopwatch()
    steps = _stage_steps(config, DESIGN_STEPS)
    swing = np.zeros((1, 6))
    swing[0, 3] = -1.0
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
    figure = _plot_lines(
        out_dir / "stage2_stable_pose.png",
        np.arange(steps) * timestep,
        [("xS", x_stable), ("zS", z_stable), ("xS_inv", 1 - x_stable), ("zS_inv", 1 - z_stable)],
        title=f"Stage 2: stable-pose neurons (front thigh swings from t = {STAGE2_SWING_FROM})",
        ylabel="activation",
    )
    before = slice(STAGE2_SWING_FROM - 50, STAGE2_SWING_FROM)
    after = slice(min(STAGE2_SWING_FROM + 50, steps - 1), steps)
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
    if stage == 3:
        backswings = [0.0]
    elif config.backswing == CheetahConfig.backswing:
        backswings = [STAGE4_DEFAULT_BACKSWING]
    else:
        backswings = list(config.backswing)
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
    figure = _plot_lines(
        out_dir / f"stage{stage}_torso.png",
        np.arange(steps) * timestep,
        [(label, traj.poses[i, :, 0, 0]) for i, label in enumerate(labels)],
        title=f"Stage {stage}: designed network, torso position",
        ylabel="torso x (m)",
        extra=[(label, traj.poses[i, :, 0, 2]) for i, label in enumerate(labels)],
        extra_ylabel="torso z (m)",
    )
    displacement = traj.torso_x[:, -1] - traj.torso_x[:, 0]
    runs = [
        {"backswing": b, "final_displacement": float(d)}
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
    return {
        "config": config_dict(config),
        "stage": stage,
        "steps": steps,
        "runs": runs,
        "artifacts": artifacts,
        "elapsed_s": watch.elapsed(),
    }


STAGES: dict[int, Callable[[CheetahConfig, Path, ProgressFn], dict[str, Any]]] = {
    0: run_stage0,
    1: run_stage1,
    2: run_stage2,
    3: lambda c, o, p: run_design_network(c, o, p, 3),
    4: lambda c, o, p: run_design_network(c, o, p, 4),
}
"""Design stage → its runner."""


if __name__ == "__main__" and sys.argv[1:2] == ["render"]:
    _render_main(Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4])
