"""Robot fish 1D: the ring-tape world and the SRD experiment (paper, "Robot fish: 1D toy
example"; docs/fish.md).

``run`` lets FishNN (agents.fish_net) live on the tape for ``steps`` steps, optionally training
it with self-reward design, and writes the energy trace and the paper's three-panel figure.
The life of the fish is one unit (``sim.units``): one sequential run has nothing to split.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from agents.fish_net import EAT, MOVE, FishNN
from agents.neurons import self_reward_loss
from sim import units
from sim.configs import FishConfig
from sim.experiment import ProgressFn, Stopwatch, no_progress
from sim.units import Decomposition, Payload, Unit

FOOD = 0.5
"""Value of a tape cell holding food (empty cells are 0)."""
TAPE = (0.0, 0.0, 0.0, 0.0, FOOD)
"""The reference's ring tape: food on every 5th cell."""
VIEW = 3
"""Cells the fish sees: its own and the two ahead."""
START_ENERGY = 1.0
"""Energy F at reset (also the cap)."""
MEAL_ENERGY = 0.5
"""Energy gained by eating food."""
STEP_COST = 0.05
"""Energy lost by every step that is not a meal (moving, or eating an empty cell)."""
ADAM_BETAS = (0.5, 0.999)
"""Adam betas of the reference's SRD optimiser."""
PLOT_WINDOW = 128
"""Steps shown in the first and last panels of the figure."""
MEAN_WINDOW = 1000
"""Window of the ``mean_energy_*_1000`` result fields."""


class RobotFish1D(gym.Env[np.ndarray, np.int64]):
    """A fish on a ring tape of cells, some holding food; it must eat to keep its energy up.

    Deterministic: no randomness anywhere (``reset(seed=...)`` accepts a seed for the API).

    **Tape**: a ring of cells, each 0 (empty) or 0.5 (food); default ``(0, 0, 0, 0, 0.5)``.
    The fish stands on the cell at ``pointer`` (0 at reset) and sees it and the next two.

    **Observation** (float32, shape (4,)): ``[e1, e2, e3, F]``, the three visible cells (e1 is
    the fish's own) and the energy F ∈ [−0.05, 1].

    **Actions** (``Discrete(2)``): 0 = EAT, 1 = MOVE.

    * EAT on food: F += 0.5 (capped at 1) and the food of the visible cell is gone (e1 = 0);
      the tape itself keeps it, so it is back when the fish comes round again.
    * MOVE: the fish advances one cell (the view rolls left); F −= 0.05.
    * EAT on an empty cell: nothing happens but F −= 0.05.

    **Reward**: the energy change of the step (after the cap): +0.5 or less for a meal, −0.05
    otherwise.

    **Episode end**: terminated when F ≤ 0 (the fish is dead); never truncated (the caller
    chooses the number of steps). A dead fish takes no step: ``step`` raises until ``reset``
    (so every observation stays in ``observation_space``).

    **Info**: ``energy`` (F after the step, full precision), ``tile`` (e1 after the step: 0.5 =
    food under the fish), ``pointer`` (tape position) and ``ate`` (the step was a meal).

    Args:
        tape: the ring of cells (each 0 or 0.5, at least ``VIEW`` cells).
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 (gymnasium's API)

    def __init__(self, tape: Sequence[float] = TAPE) -> None:
        if len(tape) < VIEW or any(cell not in (0.0, FOOD) for cell in tape):
            raise ValueError(f"tape must hold at least {VIEW} cells, each 0 or {FOOD}: {tape!r}")
        self.tape = tuple(float(cell) for cell in tape)
        self.observation_space = spaces.Box(
            low=np.array([0.0, 0.0, 0.0, -STEP_COST], dtype=np.float32),
            high=np.array([FOOD, FOOD, FOOD, START_ENERGY], dtype=np.float32),
            dtype=np.float32,
        )
        self.action_space = spaces.Discrete(2)
        self.pointer = 0
        self.energy = START_ENERGY
        self.cells = list(self.tape[:VIEW])

    def _observation(self) -> np.ndarray:
        return np.array([*self.cells, self.energy], dtype=np.float32)

    def _info(self, ate: bool) -> dict[str, Any]:
        return {"energy": self.energy, "tile": self.cells[0], "pointer": self.pointer, "ate": ate}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Back to pointer 0 with full energy."""
        super().reset(seed=seed)
        self.pointer = 0
        self.energy = START_ENERGY
        self.cells = list(self.tape[:VIEW])
        return self._observation(), self._info(ate=False)

    def step(self, action: int | np.int64) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """One step: energy from the cells before the action, then the tape moves."""
        if action not in (EAT, MOVE):
            raise ValueError(f"action must be {EAT} (eat) or {MOVE} (move), got {action!r}")
        if self.energy <= 0.0:
            raise RuntimeError("the fish is dead (its energy reached 0): call reset() first")
        before = self.energy
        ate = action == EAT and self.cells[0] == FOOD
        self.energy = min(before + MEAL_ENERGY if ate else before - STEP_COST, START_ENERGY)
        if ate:
            self.cells[0] = 0.0
        elif action == MOVE:
            self.pointer = (self.pointer + 1) % len(self.tape)
            self.cells = [self.tape[(self.pointer + k) % len(self.tape)] for k in range(VIEW)]
        terminated = self.energy <= 0.0
        return self._observation(), self.energy - before, terminated, False, self._info(ate)


ENV_ID = "RobotFish1D-v0"
"""``gymnasium.make(ENV_ID)`` builds ``RobotFish1D`` once ``sim.fish`` is imported."""
if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="sim.fish:RobotFish1D")


class FishTrace(NamedTuple):
    """What one run of the fish recorded, one entry per lived step."""

    energy: np.ndarray
    """Energy F after each step."""
    tile: np.ndarray
    """Visible cell e1 after each step (0.5 = food under the fish)."""
    meals: int
    """Steps on which the fish ate food."""
    died_at: int | None
    """Step at which the energy reached 0, or None."""


def simulate(
    config: FishConfig, progress: ProgressFn = no_progress, *, tape: Sequence[float] = TAPE
) -> FishTrace:
    """Let FishNN live on ``tape`` for ``config.steps`` steps (fewer if it dies).

    Each step's action is the greedy decision of the weights of that moment. With SRD, the
    weights change only at the end of each memory window, so the window's verdicts [T, F] are
    computed in one batch from its stored observations, summed into z and trained on
    CEL(z, argmax z) after the window's last action. This is the reference's one verdict per
    step up to float32 rounding (checked: the same 12000-step energy trace).
    Runs on one torch thread (tiny tensors: more threads only add synchronisation).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _simulate(config, progress, RobotFish1D(tape))
    finally:
        torch.set_num_threads(threads)


def _simulate(config: FishConfig, progress: ProgressFn, env: RobotFish1D) -> FishTrace:
    net = FishNN()
    observation, _ = env.reset(seed=config.seed)
    optimizer = (
        torch.optim.Adam(net.parameters(), lr=config.lr, betas=ADAM_BETAS) if config.srd else None
    )
    energy = np.zeros(config.steps)
    tile = np.zeros(config.steps)
    window_inputs: list[torch.Tensor] = []
    meals, died_at = 0, None
    report_every = max(1, config.steps // 40)
    for step in range(config.steps):
        x = torch.from_numpy(observation).view(1, 4)
        with torch.inference_mode():
            action = int(net.decide(x))
        if optimizer is not None:
            window_inputs.append(x)
            if len(window_inputs) == config.memory:
                _, verdicts = net(torch.cat(window_inputs))
                optimizer.zero_grad()
                self_reward_loss(verdicts.sum(dim=0, keepdim=True)).backward()
                optimizer.step()
                window_inputs.clear()
        observation, _, dead, _, info = env.step(action)
        energy[step], tile[step] = info["energy"], info["tile"]
        meals += info["ate"]
        if dead:
            died_at = step
            break
        if (step + 1) % report_every == 0:
            fraction = 0.95 * (step + 1) / config.steps  # the rest is for the artifacts
            progress(fraction, f"step {step + 1}, energy {info['energy']:.2f}")
    lived = config.steps if died_at is None else died_at + 1
    return FishTrace(energy[:lived], tile[:lived], meals, died_at)


def window_means(values: np.ndarray, window: int) -> np.ndarray:
    """Means over consecutive windows; the last partial window is padded with its last value."""
    padded = np.concatenate((values, np.full(-len(values) % window, values[-1])))
    return np.asarray(padded.reshape(-1, window).mean(axis=1))


def write_trace(path: Path, energy: np.ndarray, tile: np.ndarray) -> None:
    """The energy trace CSV: ``step, energy, tile`` (tile = food under the fish after the step)."""
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(("step", "energy", "tile"))
        rounded = energy.round(6) + 0.0  # a dead fish's -0.0 is written 0.0
        writer.writerows(zip(range(len(energy)), rounded, tile, strict=True))


def plot(path: Path, energy: np.ndarray, tile: np.ndarray, config: FishConfig) -> None:
    """The paper's figure: (A) first and (B) last 128 steps, (C) energy averaged over windows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    label = "SRD" if config.srd else "untrained"
    fig, axes = plt.subplots(3, 1, figsize=(8, 7.5), constrained_layout=True)
    n = len(energy)
    shown = min(PLOT_WINDOW, n)
    for ax, start, title in (
        (axes[0], 0, f"(A) first {shown} steps"),
        (axes[1], n - shown, f"(B) last {shown} steps (of {n})"),
    ):
        steps = np.arange(start, start + shown)
        ax.plot(steps, energy[start : start + shown], color="tab:blue", label="energy F")
        ax.plot(steps, tile[start : start + shown], color="tab:red", lw=0.8, label="food here")
        ax.set_ylim(-0.02, 1.2)
        ax.set_title(f"{title}, {label}")
        ax.set_xlabel("step")
        ax.legend(loc="upper right", ncols=2, fontsize=8)
    averaged = window_means(energy, config.average_every)
    axes[2].plot(np.arange(len(averaged)) * config.average_every, averaged, color="tab:blue")
    axes[2].set_ylim(0.0, 1.05)
    axes[2].set_title(f"(C) energy averaged over windows of {config.average_every} steps")
    axes[2].set_xlabel("step")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plan_fish(config: FishConfig) -> list[Unit]:
    """One unit: the whole life."""
    return [Unit("life", weight=config.steps)]


def compute_fish(config: FishConfig, unit: Unit, progress: ProgressFn) -> Payload:
    """Simulate; the trace as arrays."""
    trace = simulate(config, progress)
    return {
        "energy": trace.energy,
        "tile": trace.tile,
        "meals": int(trace.meals),
        "died_at": trace.died_at,
    }


def assemble_fish(
    config: FishConfig,
    plan: Sequence[Unit],
    payloads: Sequence[Payload],
    *,
    out_dir: Path,
    progress: ProgressFn,
    watch: Stopwatch,
) -> dict[str, Any]:
    """Write ``energy.csv`` and ``fish.png`` into ``out_dir``, return the summary.

    ``mean_energy_first_1000`` / ``mean_energy_last_1000`` average the first / last 1000
    recorded steps, or all of them when fewer were recorded (short runs, early death);
    ``mean_energy_per_1000`` lists the means of consecutive 1000-step windows (the last one may
    be shorter). ``died_at_step`` is the 0-based step at which the energy reached 0, or null.
    """
    (life,) = payloads
    energy, died_at = life["energy"], life["died_at"]
    progress(0.0, "writing energy.csv and fish.png")
    out_dir.mkdir(parents=True, exist_ok=True)
    write_trace(out_dir / "energy.csv", energy, life["tile"])
    plot(out_dir / "fish.png", energy, life["tile"], config)
    per_window = [
        float(chunk.mean())
        for chunk in np.split(energy, range(MEAN_WINDOW, len(energy), MEAN_WINDOW))
    ]
    return {
        "steps": config.steps,
        "srd": config.srd,
        "seed": config.seed,
        "died": died_at is not None,
        "died_at_step": died_at,
        "mean_energy_first_1000": round(float(energy[:MEAN_WINDOW].mean()), 6),
        "mean_energy_last_1000": round(float(energy[-MEAN_WINDOW:].mean()), 6),
        "mean_energy": round(float(energy.mean()), 6),
        "min_energy": round(float(energy.min()), 6) + 0.0,  # a death at −3e−16: 0, not −0
        "meals": life["meals"],
        "mean_energy_per_1000": [round(m, 6) for m in per_window],
        "elapsed_s": watch.elapsed(),
    }


FISH_UNITS = Decomposition(plan_fish, compute_fish, assemble_fish)
"""The fish's life as one unit."""


def run(config: FishConfig, *, out_dir: Path, progress: ProgressFn = no_progress) -> dict[str, Any]:
    """Simulate here, write ``energy.csv`` and ``fish.png`` into ``out_dir``, return the summary
    (see ``assemble_fish``)."""
    return units.run(FISH_UNITS, config, out_dir=out_dir, progress=progress)
