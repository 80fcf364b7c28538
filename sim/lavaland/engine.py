"""The robot in its world, batched: projects, map sets, the 9:1 coins and evaluation."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from agents.planning import MOVE_LIMIT, PRESETS
from agents.robot2nn import (
    EXPLORATION,
    UNKNOWN_CLASS,
    Receptors,
    Robot2NN,
    imagine,
    receptors,
)
from sim.lavaland.world import Maps, generate_maps, walk

EVAL_CHUNK = 1024
"""Maps evaluated per batch (keeps the working tensors cache-sized)."""


@dataclass(frozen=True)
class Project:
    """One of the paper's project settings (Table 1)."""

    p_target: float
    p_dirt: float
    p_grass: float
    unknown_avoidance: float
    lava_fraction: float


PROJECTS: dict[str, Project] = {
    # name:                p_target, p_dirt, p_grass, u_a, lava fraction
    "A": Project(2.0, 0.2, -0.8, 2.0, 0.0),
    "compare-A": Project(10.0, 0.2, -0.8, 2.0, 0.0),
    "lava-A": Project(10.0, 0.2, -0.8, 2.0, 0.1),
    "lava-noav-A": Project(10.0, 0.2, -0.8, 0.0, 0.1),
}
"""Project A (p_target 2), Compare A (p_target 10), Lava A (10 % lava, u_a 2), Lava NOAV A
(u_a 0). u_a is irrelevant without lava."""


def build_model(
    project: Project, preset: str, n_plans: int = 0, loss_guard: bool = False
) -> Robot2NN:
    """A fresh, identically initialised Robot2NN for a project and preset (n_plans 0 = the
    preset's), with or without the guarded loss."""
    rules = replace(PRESETS[preset], loss_guard=loss_guard)
    return Robot2NN(
        p_target=project.p_target,
        p_dirt=project.p_dirt,
        p_grass=project.p_grass,
        unknown_avoidance=project.unknown_avoidance,
        rules=replace(rules, n_plans=n_plans or rules.n_plans),
    )


def load_kernels(model: Robot2NN, stack: np.ndarray) -> None:
    """Set the 180 weights of ``model`` from a ``kernel_stack()`` array (4, 5, 3, 3)."""
    with torch.no_grad():
        for c, sequence in enumerate(model.sequences()):
            for layer, kernel in enumerate(sequence.kernels()):
                kernel.copy_(torch.tensor(stack[c, layer]).reshape(kernel.shape))


@dataclass(frozen=True)
class MapSet:
    """Maps and what the robot registered of them (its receptors of the observation)."""

    maps: Maps
    seen: Receptors

    def __len__(self) -> int:
        return len(self.maps)

    def select(self, index: int | slice) -> MapSet:
        """Some of the maps (an int keeps a batch of one)."""
        return MapSet(self.maps.select(index), self.seen.select(index))


def register(maps: Maps) -> MapSet:
    """Let the robot register maps: its receptors of exactly what the env observes."""
    rgb, self_position = maps.observe()
    return MapSet(maps, receptors(torch.from_numpy(rgb), torch.from_numpy(self_position)))


def make_maps(n: int, project: Project, rng: np.random.Generator) -> MapSet:
    """Generate n maps of a project and register them."""
    return register(generate_maps(n, project.lava_fraction, rng=rng))


def explore_coins(rng: np.random.Generator, n_maps: int, n_plans: int) -> torch.Tensor:
    """The 9:1 coins, (N, P, MOVE_LIMIT) bool: True = take the second-best move."""
    return torch.from_numpy(rng.random((n_maps, n_plans, MOVE_LIMIT)) < EXPLORATION)


@dataclass(frozen=True)
class Evaluation:
    """The executed plan of every evaluation map, walked in the world."""

    reached: np.ndarray
    """(N,) bool: the target was entered within the preset's detection horizon."""
    n_moves: np.ndarray
    """(N,) int."""
    tile_counts: np.ndarray
    """(N, 4) int: target, dirt, grass, lava among the start and the tiles entered."""

    @property
    def accuracy(self) -> float:
        """Fraction of maps whose executed plan reached the target."""
        return float(self.reached.mean())

    @property
    def lava_entered(self) -> float:
        """Fraction of maps whose executed plan entered lava at least once."""
        return float((self.tile_counts[:, UNKNOWN_CLASS] > 0).mean())


def evaluate(
    model: Robot2NN, maps: MapSet, explore: torch.Tensor, chunk: int = EVAL_CHUNK
) -> Evaluation:
    """Imagine ``explore.shape[1]`` plans per map, batched, and walk the executed ones."""
    reached, n_moves, counts = [], [], []
    with torch.no_grad():
        for lo in range(0, len(maps), chunk):
            part = maps.select(slice(lo, lo + chunk))
            plans = imagine(
                model.v_sigma(part.seen), part.seen, explore[lo : lo + chunk], model.rules
            )
            rows = torch.arange(plans.actions.shape[0])
            actions = plans.actions[rows, plans.executed(model.rules)].numpy()
            walked = walk(part.maps, actions)
            horizon = model.rules.detection_horizon
            reached.append((walked.reached_at > 0) & (walked.reached_at <= horizon))
            n_moves.append(walked.n_moves)
            counts.append(walked.tile_counts)
    return Evaluation(np.concatenate(reached), np.concatenate(n_moves), np.concatenate(counts))
