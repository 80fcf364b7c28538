"""The batched simulator: every trial of an experiment stepped together.

MuJoCo's native rollout steps every trial's state in parallel threads for one stretch of
constant control (25 steps between two decisions), then one batched controller call (the
network with the SRD updates of the trials that learn) produces the next stretch's controls.
The world (model, loop conventions) is ``sim.cheetah.world``'s, as in the env.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import rollout

from agents.cheetah_net import ACTUATORS, BODIES
from sim.cheetah.world import START_X, build_model, chunk_ends
from sim.experiment import ProgressFn, no_progress

PROGRESS_REPORTS = 40
"""Progress reports per drive."""

_FULL_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS.value


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
        threads: worker threads of the rollout pool (1 = the calling thread), at most the
            CPUs this process may run on (more would only queue: the trials' numbers do not
            depend on the thread count).
    """

    def __init__(self, n: int, *, start_x: float = START_X, threads: int = 2) -> None:
        self.model = build_model(start_x)
        self.n = n
        self.timestep = float(self.model.opt.timestep)
        self._qvel = slice(1 + self.model.nq, 1 + self.model.nq + self.model.nv)
        threads = min(
            threads, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
        )
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

    The chunk before a decision at iteration t ends with step t, so the controller sees exactly
    the pose a per-step loop reads after its t-th ``mj_step``; the control it returns is used
    from step t + 1 on (the one-step delay of the reference).
    """
    batch.reset()
    torso_x = np.empty((batch.n, steps))
    poses = np.empty((batch.n, steps, len(BODIES), 3)) if record_poses else None
    qpos = None
    if keep_qpos_of is not None:
        qpos = np.empty((steps + 1, batch.model.nq))
        qpos[0] = batch.qpos()[keep_qpos_of]
    control = np.zeros((batch.n, len(ACTUATORS)))
    decisions = set(controller_steps)
    start = 0
    for end in chunk_ends(steps, decisions):
        positions = batch.advance(control, end - start + 1)
        torso_x[:, start : end + 1] = positions[:, :, 0, 0]
        if poses is not None:
            poses[:, start : end + 1] = positions
        if qpos is not None:
            qpos[start + 1 : end + 2] = batch.chunk_qpos[keep_qpos_of]
        if end in decisions:
            control = controller(end, positions[:, -1])
        if (end + 1) * PROGRESS_REPORTS // steps > start * PROGRESS_REPORTS // steps:
            progress((end + 1) / steps, f"step {end + 1}/{steps}")
        start = end + 1
    return Trajectories(torso_x=torso_x, poses=poses, qpos=qpos)
