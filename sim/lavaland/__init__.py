"""Lavaland: the 2D robot's world and the SRD experiment (paper, "2D robot lavaland" and
appendix "2D Robot in Lavaland", Table 1).

Modules, one job each:

* ``world``: the one model of the world: tiles, map generation, moves, observations, walks.
* ``env``: the Gymnasium env ``Lavaland-v0`` over that world.
* ``engine``: the robot in its world, batched: projects, map sets, coins, evaluation.
* ``training``: SRD training, one SGD step per map.
* ``experiment``: ``LavalandConfig`` and ``run`` (the CLI command and the ``lavaland`` job).
* ``plots``: histograms, weights and the trajectory GIF.

Random streams (numpy ``default_rng`` seeded with a list, so streams never overlap):
evaluation maps ``[seed, 0]``; training maps ``[seed, 1]``; for repeat r: untrained evaluation
coins ``[seed, 2, r]``, training order and coins ``[seed, 3, r]``, SRD evaluation coins
``[seed, 4, r]``; the GIF's coins ``[seed, 5]``. Repeats share the maps (as the reference's
expts 1-4 shared their data files) and differ in coins and training order.
"""

from __future__ import annotations

import gymnasium as gym

from sim.lavaland.env import Lavaland
from sim.lavaland.experiment import LavalandConfig, run

__all__ = ["Lavaland", "LavalandConfig", "run"]

if "Lavaland-v0" not in gym.registry:
    gym.register(id="Lavaland-v0", entry_point="sim.lavaland.env:Lavaland")
