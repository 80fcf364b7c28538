"""``HalfCheetahRunStop``: one half-cheetah as a Gymnasium environment, the world HalfCheetahSRD
drives (``gymnasium.make("HalfCheetahRunStop-v0")`` once ``sim.cheetah`` is imported)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from agents.cheetah_net import LIMBS
from sim.cheetah.world import (
    START_X,
    WARMUP_STEPS,
    build_model,
    chunk_ends,
    evaluation_steps,
    inhibitor_active,
    relative_pose,
)
from sim.configs import TRIAL_STEPS


def _limb_reach(model: mujoco.MjModel) -> np.ndarray:
    """Per limb (bthigh … ffoot), the largest distance its origin can have from the torso's:
    the summed lengths of the links between them."""
    torso = model.body("torso").id
    reach = []
    for limb in LIMBS:
        body, length = model.body(limb).id, 0.0
        while body != torso:
            length += float(np.linalg.norm(model.body_pos[body]))
            body = int(model.body_parentid[body])
        reach.append(length)
    return np.array(reach)


class HalfCheetahRunStop(gym.Env[np.ndarray, np.ndarray]):
    """MuJoCo's half-cheetah asked to run forward, and to stand still while a stop command is on.

    **Model**: Gymnasium's ``half_cheetah.xml`` with the paper's edits (``sim.cheetah.world``,
    the same model as the batched engine's): the torso starts at (``start_x``, 0, 0.7), the
    floor lies at z = −0.5, so the cheetah drops about 0.5 m and lands. One ``mj_step`` is
    0.01 s; there is no frame skip.

    **Timing**: one env step is one decision of the controller.

    * ``reset`` runs iterations t = 0 … 101 with zero control (the 100-step warm-up in which
      the cheetah lands, then the first decision's iteration); the first observation is read
      at t = 101.
    * ``step`` applies the action from iteration t + 1 and holds it 25 iterations, up to the
      next decision at t + 25 (the last step runs to the end of the episode).
    * An iteration is ``mj_step`` then a read of the body positions, which are the kinematics
      of the state that step started from: an action acts with a one-step (10 ms) delay, as in
      the paper's reference loop.

    **Observation** (float64, shape (13,)):

    ====== =====================================================================
    index  meaning
    ====== =====================================================================
    0–5    x of bthigh, bshin, bfoot, fthigh, fshin, ffoot minus the torso's (m)
    6–11   z of the same bodies minus the torso's (m)
    12     stop command: 1 when on at this decision (t > 500 and t mod 1000 < 600)
    ====== =====================================================================

    Positions are the body-frame origins in world coordinates (HalfCheetahSRD's input u is
    entries 0–11). Each is bounded by the limb's reach: the summed lengths of the links from
    the torso to it (0.5 m for the thighs, 1.11 m for the back foot).

    **Actions** (``Box(−1, 1, (6,), float32)``): torques of bt, bs, bf, ft, fs, ff (back thigh,
    shin, foot, front thigh, shin, foot; gears 120, 90, 60, 120, 60, 30); MuJoCo clamps them to
    [−1, 1].

    **Reward**: with v = (torso x after the step − before) / time the action was held: v when
    the stop command was off at the decision (run), −|v| when it was on (stand still).

    **Starting state**: qpos = qvel = 0 (torso at (``start_x``, 0, 0.7)), plus uniform noise in
    ±``reset_noise_scale`` on qpos and ``reset_noise_scale`` · N(0, 1) on qvel, drawn from
    ``np_random`` (scale 0: the paper's exact start, and the env is deterministic).

    **Episode end**: never terminated; truncated when iteration ``steps`` − 1 is reached (after
    140 decisions for 3600 steps).

    **Info**: ``t`` (iteration of the observed pose), ``x_position`` (torso x of that pose, m)
    and ``stop_command``; after a step also ``x_velocity`` (v, m/s), ``reward_run`` and
    ``reward_stop`` (their sum is the reward).

    Args:
        start_x: torso start x (the main experiment's −2; the design stages use −1).
        steps: iterations of 0.01 s per episode (at least 103: the warm-up, a decision and one
            step of its control).
        reset_noise_scale: scale of the start-state noise (0: none).
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 (gymnasium's API)

    def __init__(
        self, start_x: float = START_X, steps: int = TRIAL_STEPS, reset_noise_scale: float = 0.0
    ) -> None:
        if steps < WARMUP_STEPS + 3:
            raise ValueError(f"steps must be at least {WARMUP_STEPS + 3}, got {steps}")
        if reset_noise_scale < 0:
            raise ValueError(f"reset_noise_scale must be ≥ 0, got {reset_noise_scale}")
        self.model = build_model(start_x)
        self.data = mujoco.MjData(self.model)
        self.steps = steps
        self.reset_noise_scale = reset_noise_scale
        self.timestep = float(self.model.opt.timestep)
        self._ends = chunk_ends(steps, evaluation_steps(steps))
        self._decision = 0
        self.t = -1
        """Iteration of the last read pose (−1 before the first reset)."""
        reach = np.tile(_limb_reach(self.model), 2)
        self.observation_space = spaces.Box(
            np.append(-reach, 0.0), np.append(reach, 1.0), dtype=np.float64
        )
        low, high = self.model.actuator_ctrlrange.T.astype(np.float32)
        self.action_space = spaces.Box(low, high, dtype=np.float32)

    def _run_to(self, t: int) -> None:
        mujoco.mj_step(self.model, self.data, t - self.t)
        self.t = t

    def _stop_command(self) -> bool:
        return inhibitor_active(self.t)

    def _observation(self) -> np.ndarray:
        return np.append(relative_pose(self.data.xpos[1:]), float(self._stop_command()))

    def _info(self) -> dict[str, Any]:
        return {
            "t": self.t,
            "x_position": float(self.data.xpos[1, 0]),
            "stop_command": self._stop_command(),
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Back to the start state, then the warm-up up to the first decision."""
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        scale = self.reset_noise_scale
        self.data.qpos[:] += self.np_random.uniform(-scale, scale, self.model.nq)
        self.data.qvel[:] += scale * self.np_random.standard_normal(self.model.nv)
        self.t, self._decision = -1, 0
        self._run_to(self._ends[0])
        return self._observation(), self._info()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Hold ``action`` up to the next decision (or the episode's last iteration)."""
        if self.t < 0 or self._decision == len(self._ends) - 1:
            raise RuntimeError("the episode is over (or not started): call reset()")
        stopped = self._stop_command()
        x_before, t_before = float(self.data.xpos[1, 0]), self.t
        self.data.ctrl[:] = action
        self._decision += 1
        self._run_to(self._ends[self._decision])
        velocity = (float(self.data.xpos[1, 0]) - x_before) / ((self.t - t_before) * self.timestep)
        reward_run = 0.0 if stopped else velocity
        reward_stop = -abs(velocity) if stopped else 0.0
        info = self._info() | {
            "x_velocity": velocity,
            "reward_run": reward_run,
            "reward_stop": reward_stop,
        }
        truncated = self.t == self.steps - 1
        return self._observation(), reward_run + reward_stop, False, truncated, info
