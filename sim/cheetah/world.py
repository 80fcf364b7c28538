"""The half-cheetah's world, defined once for the env and the batched engine.

The model is Gymnasium's ``half_cheetah.xml`` with the reference's four edits: the torso
starts at x = −2 (−1 in the design stages), the floor lies at z = −0.5 (so the cheetah drops
~0.5 m and settles), the floor is drawn 15 m wide and its checker is grey. Seven position
sensors report the body origins so the batched rollout hands back the pose of every step; they
do not touch the physics.

The loop conventions, per iteration t = 0, 1, …, steps − 1:

1. ``mj_step`` with the current control (one step is 0.01 s);
2. read the body positions: the kinematics of the state *before* this step's integration, so
   a control computed from them acts with a one-step (10 ms) delay;
3. for t ≤ ``WARMUP_STEPS`` the control stays zero (the cheetah lands); at the decision steps
   t = 101 + 25k a new control is computed from the pose just read, applied from step t + 1
   and held ``CONTROL_INTERVAL`` steps;
4. the stop command is on when t > 500 and t mod 1000 < 600.
"""

from __future__ import annotations

import importlib.resources
import warnings
from collections.abc import Iterable
from pathlib import Path

import mujoco
import numpy as np

from agents.cheetah_net import BODIES

START_X = -2.0
"""Torso start x in the main experiment (Gymnasium: 0)."""
DESIGN_START_X = -1.0
"""Torso start x in the design stages 0–4."""
START_Z = 0.7
"""Torso start height (Gymnasium's)."""
FLOOR_Z = -0.5
"""Floor height (Gymnasium: 0): the cheetah starts ~0.5 m higher and drops onto it."""
FLOOR_SIZE = 15.0
"""Drawn floor half-size (planes collide everywhere; rendering only)."""
CHECKER_GREY = 0.4
"""First checker colour of the floor texture (Gymnasium: black; cosmetic)."""

WARMUP_STEPS = 100
"""Zero control for t ≤ WARMUP_STEPS: the cheetah lands and settles."""
CONTROL_INTERVAL = 25
"""Steps a computed control is held before the next decision (the reference's momentum)."""
INHIBITOR_FROM = 500
"""The stop-command schedule starts after this step ..."""
INHIBITOR_PERIOD = 1000
"""... and in every period of this many steps ..."""
INHIBITOR_WINDOW = 600
"""... it is on for the first this many steps."""


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
    spec.body("torso").pos = [start_x, 0.0, START_Z]
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


def evaluation_steps(steps: int) -> list[int]:
    """The decision steps: t = 101 + 25k < steps."""
    return list(range(WARMUP_STEPS + 1, steps, CONTROL_INTERVAL))


def chunk_ends(steps: int, decisions: Iterable[int]) -> list[int]:
    """Last iteration of each stretch of constant control: every decision in [0, steps), then
    the final iteration."""
    ends = [t for t in sorted(set(decisions)) if 0 <= t < steps]
    return ends if ends and ends[-1] == steps - 1 else [*ends, steps - 1]


def inhibitor_active(t: int) -> bool:
    """True when the stop command is on at iteration t (t > 500 and t mod 1000 < 600)."""
    return t > INHIBITOR_FROM and t % INHIBITOR_PERIOD < INHIBITOR_WINDOW


def stop_windows(steps: int) -> list[tuple[int, int]]:
    """The [first, last] iterations of each stretch of the stop command below ``steps``."""
    windows = []
    for period in range(0, steps, INHIBITOR_PERIOD):
        first = max(period, INHIBITOR_FROM + 1)
        last = min(period + INHIBITOR_WINDOW, steps) - 1
        if first <= last:
            windows.append((first, last))
    return windows
