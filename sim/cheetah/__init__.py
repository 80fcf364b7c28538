"""MuJoCo's half-cheetah driven by HalfCheetahSRD (the paper's "MuJoCo with SRD").

Modules, one job each:

* ``world``: the MuJoCo model and the loop conventions, shared by the env and the engine;
* ``env``: ``HalfCheetahRunStop``, one cheetah as a Gymnasium env (``HalfCheetahRunStop-v0``);
* ``engine``: ``HalfCheetahBatch`` and ``drive``, every trial stepped together;
* ``config``: the grid's cells and the result shape (``CheetahConfig``, the knobs, is in
  ``sim.configs``);
* ``experiment``: ``run``, the seeded grid, its statistics and artifacts;
* ``stages``: the appendix's design stages 0–4;
* ``plots``: the figures;
* ``render``: the GIF of one trial (``python -m sim.cheetah.render`` in a child process).

``CheetahConfig`` and ``run`` are the experiment's entry points (the CLI and the job backend
use them). The package loads them on first use: importing it only registers the env, so
``python -m sim.cheetah.render`` (the GIF's child process) runs its module once and without
the experiment.
"""

from __future__ import annotations

import importlib
import os
from typing import TYPE_CHECKING, Any

import gymnasium as gym

RENDER_CHILD = "SRD_CHEETAH_RENDER_CHILD"
"""Set in the environment of the GIF's child process (``render``), which picks its back end."""
if os.environ.get(RENDER_CHILD) != "1":
    # MuJoCo binds an OpenGL back end when it is imported, and fails to import if the one
    # MUJOCO_GL names is missing (``osmesa`` without its library). The simulation draws
    # nothing: only the GIF's child process, which sets its own, needs one.
    os.environ["MUJOCO_GL"] = "disable"

if TYPE_CHECKING:
    from sim.cheetah.env import HalfCheetahRunStop
    from sim.cheetah.experiment import run
    from sim.configs import CheetahConfig

__all__ = ["CheetahConfig", "HalfCheetahRunStop", "run"]

ENV_ID = "HalfCheetahRunStop-v0"
"""The env's Gymnasium id."""

_EXPORTS = {
    "CheetahConfig": "sim.configs",
    "HalfCheetahRunStop": "sim.cheetah.env",
    "run": "sim.cheetah.experiment",
}

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="sim.cheetah.env:HalfCheetahRunStop")


def __getattr__(name: str) -> Any:
    """Load ``CheetahConfig``, ``HalfCheetahRunStop`` and ``run`` from their modules on first
    use."""
    if name not in _EXPORTS:
        raise AttributeError(f"module 'sim.cheetah' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
