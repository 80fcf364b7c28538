"""Lavaland: the 2D robot's world and the SRD experiment (paper, "2D robot lavaland" and
appendix "2D Robot in Lavaland", Table 1; spec lavaland.md).

``run`` evaluates an untrained Robot2NN (agents.robot2nn) on stored evaluation maps, trains it
with self-reward design for one epoch (one map per SGD step), evaluates it again, and writes the
accuracy table, the tile histograms, the 180 weights and a trajectory GIF.

Random streams (numpy ``default_rng`` seeded with a list, so streams never overlap):
evaluation maps ``[seed, 0]``; training maps ``[seed, 1]``; for repeat r: untrained evaluation
coins ``[seed, 2, r]``, training order and coins ``[seed, 3, r]``, SRD evaluation coins
``[seed, 4, r]``; the GIF's coins ``[seed, 5]``. Repeats share the maps (as the reference's
expts 1-4 shared their data files) and differ in coins and training order.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any, Literal

import gymnasium as gym
import matplotlib
import numpy as np
import torch
from gymnasium import spaces
from PIL import Image, ImageDraw
from pydantic import Field

from agents.robot2nn import (
    DIRT_CLASS,
    EXPLORATION,
    GRASS_CLASS,
    MOVE_LIMIT,
    NAMED_INPUTS,
    PRESETS,
    UNKNOWN_CLASS,
    Plans,
    Receptors,
    Robot2NN,
    imagine,
    receptors,
)
from sim.experiment import ProgressFn, Stopwatch, no_progress, write_json

matplotlib.use("Agg")
import matplotlib.pyplot as plt

MAP_HEIGHT = 11
"""Rows H of a map (the reference's ``--map_size 11 13``)."""
MAP_WIDTH = 13
"""Columns W of a map."""
GRASS_FRACTION = 0.3
"""Probability g that a tile is grass."""
TARGET, DIRT, GRASS, LAVA = 0, 1, 2, 3
"""Tile ids."""
TILE_NAMES = ("target", "dirt", "grass", "lava")
"""Tile names by id."""
TILE_RGB = np.array([(255, 215, 0), (139, 69, 19), (0, 128, 0), (255, 0, 0)], dtype=np.uint8)
"""Tile colours by id (0-255): yellow target, brown dirt, green grass, red lava."""
TILE_CHARS = "T.gL"
"""Tile ids as map-string characters; ``S`` marks the start (a dirt tile)."""
START_CHAR = "S"
"""The start tile in a map string."""
ACTION_NAMES = ("right", "down", "left", "up")
"""Actions 0-3."""
ACTION_STEPS = ((1, 0), (0, 1), (-1, 0), (0, -1))
"""(dx, dy) of each action; x is the column, y the row."""
EVAL_CHUNK = 1024
"""Maps evaluated per batch (keeps the working tensors cache-sized)."""


def generate_tiles(
    n: int,
    lava_fraction: float,
    grass_fraction: float = GRASS_FRACTION,
    *,
    rng: np.random.Generator,
    height: int = MAP_HEIGHT,
    width: int = MAP_WIDTH,
) -> tuple[np.ndarray, np.ndarray]:
    """n maps as tile ids (N, H, W) int8 and starts (N, 2) = (x, y), spec §1 vectorised.

    Draw order: start x then y; one uniform array (grass where < g) or, with lava, a first
    uniform array ("special" where < g + l) and a second uniform(0, g + l) one (grass where < g,
    else lava); targets x then y, redrawn where they hit the start; start forced to dirt.
    For n = 1 this is exactly the reference's sequence of draws.
    """
    start_x = rng.integers(0, width, size=n)
    start_y = rng.integers(0, height, size=n)
    tiles = np.full((n, height, width), DIRT, dtype=np.int8)
    if lava_fraction == 0:
        tiles[rng.random((n, height, width)) < grass_fraction] = GRASS
    else:
        special = rng.random((n, height, width)) < grass_fraction + lava_fraction
        kind = rng.uniform(0.0, grass_fraction + lava_fraction, size=(n, height, width))
        tiles[special] = np.where(kind[special] < grass_fraction, GRASS, LAVA)
    target_x = rng.integers(0, width, size=n)
    target_y = rng.integers(0, height, size=n)
    clash = (target_x == start_x) & (target_y == start_y)
    while clash.any():
        target_x[clash] = rng.integers(0, width, size=int(clash.sum()))
        target_y[clash] = rng.integers(0, height, size=int(clash.sum()))
        clash = (target_x == start_x) & (target_y == start_y)
    rows = np.arange(n)
    tiles[rows, start_y, start_x] = DIRT
    tiles[rows, target_y, target_x] = TARGET
    return tiles, np.stack([start_x, start_y], axis=1).astype(np.int64)


def tiles_to_rgb(tiles: np.ndarray) -> np.ndarray:
    """Tile ids (..., H, W) → RGB in [0, 1], float32 (..., 3, H, W)."""
    rgb = TILE_RGB[tiles].astype(np.float32) / 255.0
    return np.moveaxis(rgb, -1, -3)


def generate_maps(
    n: int,
    lava_fraction: float,
    grass_fraction: float = GRASS_FRACTION,
    *,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """n 11×13 maps as RGB arrays (N, 3, H, W) float32 in [0, 1] and starts (N, 2) = (x, y)."""
    tiles, starts = generate_tiles(n, lava_fraction, grass_fraction, rng=rng)
    return tiles_to_rgb(tiles), starts


def parse_map(rows: Sequence[str]) -> tuple[np.ndarray, tuple[int, int]]:
    """Map strings ("T" target, "." dirt, "g" grass, "L" lava, "S" start) → tile ids, (x, y)."""
    if not rows or len({len(r) for r in rows}) != 1:
        raise ValueError("a map is a non-empty list of strings of equal length")
    text = "".join(rows)
    if text.count(START_CHAR) != 1 or text.count("T") != 1:
        raise ValueError("a map needs exactly one start 'S' and one target 'T'")
    unknown = set(text) - set(TILE_CHARS + START_CHAR)
    if unknown:
        raise ValueError(f"unknown map characters {sorted(unknown)}; use {TILE_CHARS!r} and 'S'")
    grid = np.array([list(r) for r in rows])
    tiles = np.full(grid.shape, DIRT, dtype=np.int8)
    for tile, char in enumerate(TILE_CHARS):
        tiles[grid == char] = tile
    y, x = np.argwhere(grid == START_CHAR)[0]
    return tiles, (int(x), int(y))


def format_map(tiles: np.ndarray, start: Sequence[int]) -> list[str]:
    """Tile ids (H, W) and start (x, y) → map strings (inverse of ``parse_map``)."""
    grid = np.array(list(TILE_CHARS))[tiles]
    grid[int(start[1]), int(start[0])] = START_CHAR
    return ["".join(row) for row in grid]


class Lavaland(gym.Env[dict[str, np.ndarray], int]):
    """A robot walks a grid of target, dirt, grass and lava tiles to the one target tile.

    **Map**: H × W tiles (default 11 × 13). Each episode draws a new map from ``np_random``
    (spec §1): the start first (uniform), every tile dirt, then grass with probability
    ``grass_fraction`` and lava with ``lava_fraction`` (i.i.d.), the target redrawn until it is
    not the start, the start forced to dirt. A fixed map can be given as strings (``map_rows``
    or ``reset(options={"map": rows})``): "T" target, "." dirt, "g" grass, "L" lava, "S" start.

    **Observation** (``Dict``): ``map`` = the RGB map, float32 (3, H, W) in [0, 1] (target
    (255, 215, 0), dirt (139, 69, 19), grass (0, 128, 0), lava (255, 0, 0), / 255); ``self`` =
    the robot's position as a one-hot float32 (H, W).

    **Actions** (``Discrete(4)``): 0 right (x + 1), 1 down (y + 1), 2 left (x − 1), 3 up
    (y − 1). A move off the grid leaves the robot where it is (it still counts as a move).

    **Reward**: 1 on entering the target, 0 otherwise. Grass and lava cost nothing here: the
    robot's preferences are its own design (agents.robot2nn), not the world's reward.

    **Episode end**: terminated on reaching the target; truncated after ``max_moves`` moves.

    **Info**: ``position`` (x, y), ``tile`` (name of the tile under the robot), ``moves``,
    ``lava_entered`` (lava tiles entered so far, with repeats) and ``reached``.

    Args:
        map_rows: a fixed map as strings (default: a new random map every episode).
        lava_fraction: probability l of lava per tile for random maps.
        grass_fraction: probability g of grass per tile for random maps.
        max_moves: moves before truncation (the paper's 36).
        height, width: size of random maps.
        render_mode: ``"rgb_array"`` or None.
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 4}  # noqa: RUF012

    def __init__(
        self,
        map_rows: Sequence[str] | None = None,
        lava_fraction: float = 0.0,
        grass_fraction: float = GRASS_FRACTION,
        max_moves: int = MOVE_LIMIT,
        height: int = MAP_HEIGHT,
        width: int = MAP_WIDTH,
        render_mode: str | None = None,
    ) -> None:
        if not (lava_fraction >= 0 and grass_fraction >= 0 and lava_fraction + grass_fraction < 1):
            raise ValueError("need 0 ≤ lava_fraction, 0 ≤ grass_fraction, their sum < 1")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']}")
        self.fixed = parse_map(map_rows) if map_rows is not None else None
        if self.fixed is not None:
            height, width = self.fixed[0].shape
        self.lava_fraction = lava_fraction
        self.grass_fraction = grass_fraction
        self.max_moves = max_moves
        self.height, self.width = height, width
        self.render_mode = render_mode
        self.observation_space = spaces.Dict(
            {
                "map": spaces.Box(0.0, 1.0, (3, height, width), dtype=np.float32),
                "self": spaces.Box(0.0, 1.0, (height, width), dtype=np.float32),
            }
        )
        self.action_space = spaces.Discrete(len(ACTION_NAMES))
        self.tiles = np.full((height, width), DIRT, dtype=np.int8)
        self.position = (0, 0)
        self.moves = 0
        self.lava_entered = 0

    def _observation(self) -> dict[str, np.ndarray]:
        one_hot = np.zeros((self.height, self.width), dtype=np.float32)
        one_hot[self.position[1], self.position[0]] = 1.0
        return {"map": tiles_to_rgb(self.tiles), "self": one_hot}

    def _info(self) -> dict[str, Any]:
        tile = int(self.tiles[self.position[1], self.position[0]])
        return {
            "position": self.position,
            "tile": TILE_NAMES[tile],
            "moves": self.moves,
            "lava_entered": self.lava_entered,
            "reached": tile == TARGET,
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        if options is not None and "map" in options:
            tiles, start = parse_map(options["map"])
            if tiles.shape != (self.height, self.width):
                raise ValueError(f"map must be {self.height}×{self.width}, got {tiles.shape}")
        elif self.fixed is not None:
            tiles, start = self.fixed
        else:
            many, starts = generate_tiles(
                1,
                self.lava_fraction,
                self.grass_fraction,
                rng=self.np_random,
                height=self.height,
                width=self.width,
            )
            tiles, start = many[0], (int(starts[0, 0]), int(starts[0, 1]))
        self.tiles = tiles.copy()
        self.position = start
        self.moves = 0
        self.lava_entered = 0
        return self._observation(), self._info()

    def step(self, action: int) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if not self.action_space.contains(action):
            raise ValueError(f"action must be 0-3 ({', '.join(ACTION_NAMES)}), got {action!r}")
        dx, dy = ACTION_STEPS[int(action)]
        x, y = self.position[0] + dx, self.position[1] + dy
        if 0 <= x < self.width and 0 <= y < self.height:
            self.position = (x, y)
        self.moves += 1
        tile = int(self.tiles[self.position[1], self.position[0]])
        self.lava_entered += int(tile == LAVA)
        reached = tile == TARGET
        truncated = not reached and self.moves >= self.max_moves
        return self._observation(), float(reached), reached, truncated, self._info()

    def render(self) -> np.ndarray | None:
        """``rgb_array``: the map, 16 px per tile, the robot as a blue cross."""
        if self.render_mode != "rgb_array":
            return None
        return picture(TILE_RGB[self.tiles], [self.position])


def picture(colours: np.ndarray, path: Sequence[tuple[int, int]], cell: int = 16) -> np.ndarray:
    """Tile colours (H, W, 3) uint8 → image (H·cell, W·cell, 3) with the path drawn in orange
    through the tile centres and the robot (last point) as a blue cross."""
    image = Image.fromarray(np.repeat(np.repeat(colours, cell, axis=0), cell, axis=1))
    draw = ImageDraw.Draw(image)
    if len(path) > 1:
        centres = [(x * cell + cell // 2, y * cell + cell // 2) for x, y in path]
        draw.line(centres, fill=(255, 140, 0), width=max(1, cell // 6))
    x, y = path[-1]
    lo_x, lo_y = x * cell + cell // 5, y * cell + cell // 5
    hi_x, hi_y = (x + 1) * cell - 1 - cell // 5, (y + 1) * cell - 1 - cell // 5
    draw.line([(lo_x, lo_y), (hi_x, hi_y)], fill=(0, 0, 255), width=max(1, cell // 8))
    draw.line([(lo_x, hi_y), (hi_x, lo_y)], fill=(0, 0, 255), width=max(1, cell // 8))
    return np.asarray(image)


if "Lavaland-v0" not in gym.registry:
    gym.register(id="Lavaland-v0", entry_point="sim.lavaland:Lavaland")


# ---------------------------------------------------------------------------------------------
# The experiment
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Project:
    """One of the paper's project settings (spec §10)."""

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


@dataclass(frozen=True)
class LavalandConfig:
    """Robot2NN in lavaland: evaluate untrained, SRD-train one epoch, evaluate again."""

    project: Literal["A", "compare-A", "lava-A", "lava-noav-A"] = "A"
    """The paper's project: A, compare-A, lava-A or lava-noav-A."""
    preset: Literal["paper", "reference"] = "paper"
    """paper: 4 plans, best plan executed, summed loss, anchors set; reference: the v1 code."""
    eval_maps: Annotated[int, Field(ge=1)] = 4096
    """Evaluation maps (accuracy = reached / eval_maps)."""
    train_maps: Annotated[int, Field(ge=0)] = 4096
    """Training maps, one SGD step each (0 skips training; accuracy_srd is then null)."""
    repeats: Annotated[int, Field(ge=1)] = 1
    """Independent experiments (the paper's expts 1-4): fresh model, coins and order each."""
    n_plans: Annotated[int, Field(ge=0)] = 0
    """Imagined plans per map; 0 = the preset's (paper 4, reference 2)."""
    lr: Annotated[float, Field(gt=0)] = 1e-4
    """SGD learning rate."""
    gif_map: Annotated[int, Field(ge=0)] = 0
    """Evaluation map (index modulo eval_maps) animated in trajectory.gif."""
    seed: int = 0
    """Seed of every random stream (maps, coins, training order)."""


@dataclass(frozen=True)
class Evaluation:
    """The executed plan of every evaluation map."""

    reached: np.ndarray
    """(N,) bool."""
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


def explore_coins(rng: np.random.Generator, n_maps: int, n_plans: int) -> torch.Tensor:
    """The 9:1 coins, (N, P, MOVE_LIMIT) bool: True = take the second-best move."""
    return torch.from_numpy(rng.random((n_maps, n_plans, MOVE_LIMIT)) < EXPLORATION)


def evaluate(
    model: Robot2NN, seen: Receptors, explore: torch.Tensor, chunk: int = EVAL_CHUNK
) -> Evaluation:
    """Imagine ``explore.shape[1]`` plans per map, batched, and keep the executed ones."""
    reached, n_moves, counts = [], [], []
    with torch.no_grad():
        for lo in range(0, explore.shape[0], chunk):
            part = seen.select(slice(lo, lo + chunk))
            plans = imagine(model.v_sigma(part), part, explore[lo : lo + chunk], model.rules)
            rows = torch.arange(plans.reached.shape[0])
            chosen = plans.executed(model.rules)
            reached.append(plans.reached[rows, chosen])
            n_moves.append(plans.n_moves[rows, chosen])
            counts.append(plans.tile_counts[rows, chosen])
    return Evaluation(
        reached=torch.cat(reached).numpy(),
        n_moves=torch.cat(n_moves).numpy(),
        tile_counts=torch.cat(counts).numpy(),
    )


def train_srd(
    model: Robot2NN,
    seen: Receptors,
    order: np.ndarray,
    explore: torch.Tensor,
    lr: float,
    progress: ProgressFn = no_progress,
) -> None:
    """One SRD epoch: for each map in ``order``, one SGD step on its own plans' loss.

    ``explore[i]`` are the coins of the i-th step (map ``order[i]``).
    """
    parameters = list(model.parameters())
    report_every = max(1, len(order) // 16)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one map's tensors are tiny: more threads only add overhead
    try:
        for step, index in enumerate(order.tolist()):
            one = seen.select(index)
            v_sigma = model.v_sigma(one)
            plans = imagine(v_sigma, one, explore[step : step + 1], model.rules)
            model.srd_loss(plans.differentiable_v_plan(v_sigma)).backward()
            with torch.no_grad():  # plain SGD: no momentum, no weight decay
                for weight in parameters:
                    if weight.grad is not None:
                        weight.sub_(weight.grad, alpha=lr)
                        weight.grad = None
            if (step + 1) % report_every == 0:
                progress((step + 1) / len(order), f"SRD step {step + 1}/{len(order)}")
    finally:
        torch.set_num_threads(threads)


def build_model(project: Project, preset: str, n_plans: int = 0) -> Robot2NN:
    """A fresh, identically initialised Robot2NN for a project and preset (n_plans 0 = the
    preset's)."""
    rules = PRESETS[preset]
    return Robot2NN(
        p_target=project.p_target,
        p_dirt=project.p_dirt,
        p_grass=project.p_grass,
        unknown_avoidance=project.unknown_avoidance,
        rules=replace(rules, n_plans=n_plans or rules.n_plans),
    )


@dataclass(frozen=True)
class Outcome:
    """One repeat: the untrained and SRD evaluations and the trained weights."""

    untrained: Evaluation
    srd: Evaluation | None
    kernels: np.ndarray | None
    """(4, 5, 3, 3) weights after SRD."""

    def row(self, repeat: int) -> dict[str, Any]:
        """This repeat's row of the accuracy table."""
        srd = self.srd
        return {
            "repeat": repeat,
            "accuracy_untrained": self.untrained.accuracy,
            "accuracy_srd": None if srd is None else srd.accuracy,
            "lava_entered_untrained": self.untrained.lava_entered,
            "lava_entered_srd": None if srd is None else srd.lava_entered,
            "mean_moves_untrained": float(self.untrained.n_moves.mean()),
            "mean_moves_srd": None if srd is None else float(srd.n_moves.mean()),
        }


def run(
    config: LavalandConfig, *, out_dir: Path, progress: ProgressFn = no_progress
) -> dict[str, Any]:
    """Evaluate → SRD-train → evaluate, ``repeats`` times; write the artifacts; return the result.

    The scalar fields are means over repeats; ``repeats`` lists one object per repeat (the
    paper's Table 1 layout: one row per expt).
    """
    clock = Stopwatch()
    project = PROJECTS[config.project]
    n_plans = config.n_plans or PRESETS[config.preset].n_plans
    out_dir.mkdir(parents=True, exist_ok=True)
    progress(0.0, "generating maps")
    eval_seen = seen_maps(config.eval_maps, project, np.random.default_rng([config.seed, 0]))
    train_seen = seen_maps(config.train_maps, project, np.random.default_rng([config.seed, 1]))
    outcomes: list[Outcome] = []
    for r in range(config.repeats):
        share = 1.0 / config.repeats

        def report(fraction: float, message: str, r: int = r, share: float = share) -> None:
            progress((r + fraction) * share, f"repeat {r + 1}: {message}")

        model = build_model(project, config.preset, n_plans)
        coins = explore_coins(np.random.default_rng([config.seed, 2, r]), config.eval_maps, n_plans)
        untrained = evaluate(model, eval_seen, coins)
        report(0.05, "untrained evaluated")
        if config.train_maps == 0:
            outcomes.append(Outcome(untrained, None, None))
            continue
        rng = np.random.default_rng([config.seed, 3, r])
        order = rng.permutation(config.train_maps)
        train_coins = explore_coins(rng, config.train_maps, n_plans)
        train_srd(
            model, train_seen, order, train_coins, config.lr, lambda f, m: report(0.05 + 0.9 * f, m)
        )
        coins = explore_coins(np.random.default_rng([config.seed, 4, r]), config.eval_maps, n_plans)
        outcomes.append(
            Outcome(
                untrained, evaluate(model, eval_seen, coins), model.kernel_stack().detach().numpy()
            )
        )
        report(1.0, "SRD evaluated")
    rows = [outcome.row(r + 1) for r, outcome in enumerate(outcomes)]
    gif_coins = explore_coins(np.random.default_rng([config.seed, 5]), 1, n_plans)
    gif_map = eval_seen.select(config.gif_map % config.eval_maps)
    artifacts = write_artifacts(out_dir, config, outcomes, model, gif_map, gif_coins)

    def mean(key: str) -> float | None:
        values = [row[key] for row in rows]
        return None if values[0] is None else float(np.mean(values))

    return {
        "project": config.project,
        "preset": config.preset,
        "n_params": sum(p.numel() for p in model.parameters() if p.requires_grad),
        "n_plans": n_plans,
        "eval_maps": config.eval_maps,
        "train_maps": config.train_maps,
        "seed": config.seed,
        "accuracy_untrained": mean("accuracy_untrained"),
        "accuracy_srd": mean("accuracy_srd"),
        "lava_entered_untrained": mean("lava_entered_untrained"),
        "lava_entered_srd": mean("lava_entered_srd"),
        "repeats": rows,
        "artifacts": artifacts,
        "elapsed_s": clock.elapsed(),
    }


def seen_maps(n: int, project: Project, rng: np.random.Generator) -> Receptors:
    """Generate n maps of a project and register them with the robot's receptors."""
    maps, starts = generate_maps(n, project.lava_fraction, rng=rng)
    return receptors(torch.from_numpy(maps), torch.from_numpy(starts))


# ---------------------------------------------------------------------------------------------
# Artifacts
# ---------------------------------------------------------------------------------------------
def write_artifacts(
    out_dir: Path,
    config: LavalandConfig,
    outcomes: list[Outcome],
    model: Robot2NN,
    gif_map: Receptors,
    gif_coins: torch.Tensor,
) -> list[str]:
    """accuracy.csv/json, tile_counts.csv, tile_histograms.png, weights.json/png, trajectory.gif
    (the GIF shows ``model``, the last repeat's robot, on ``gif_map``)."""
    rows = [outcome.row(r + 1) for r, outcome in enumerate(outcomes)]
    with (out_dir / "accuracy.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    write_json(out_dir / "accuracy.json", rows)
    with (out_dir / "tile_counts.csv").open("w", newline="") as handle:
        table = csv.writer(handle)
        table.writerow(["repeat", "model", "map", "reached", "n_moves", "dirt", "grass", "lava"])
        for r, outcome in enumerate(outcomes):
            for label, ev in (("untrained", outcome.untrained), ("srd", outcome.srd)):
                if ev is None:
                    continue
                for i, counts in enumerate(ev.tile_counts[:, DIRT_CLASS:].tolist()):
                    table.writerow(
                        [r + 1, label, i, int(ev.reached[i]), int(ev.n_moves[i]), *counts]
                    )
    plot_histograms(out_dir / "tile_histograms.png", config, outcomes)
    initial = build_model(PROJECTS[config.project], config.preset).kernel_stack().detach().numpy()
    trained = [o.kernels for o in outcomes if o.kernels is not None]
    write_json(
        out_dir / "weights.json",
        {
            "layout": "[DeconvSeq self/target/dirt/grass][layer 1-5][3][3]",
            "initial": initial.tolist(),
            "srd": [w.tolist() for w in trained],
        },
    )
    panels = [("initial", initial)] + [
        (f"after SRD, repeat {r + 1} (acc {o.srd.accuracy:.3f})", o.kernels)
        for r, o in enumerate(outcomes)
        if o.srd is not None and o.kernels is not None
    ]
    plot_weights(out_dir / "weights.png", panels)
    trajectory_gif(out_dir / "trajectory.gif", model, gif_map, gif_coins)
    return [
        "accuracy.csv",
        "accuracy.json",
        "tile_counts.csv",
        "tile_histograms.png",
        "weights.json",
        "weights.png",
        "trajectory.gif",
    ]


def plot_histograms(path: Path, config: LavalandConfig, outcomes: list[Outcome]) -> None:
    """Cumulative histograms of dirt / grass (/ lava) tiles traversed, repeats pooled."""
    classes = [(DIRT_CLASS, "dirt"), (GRASS_CLASS, "grass")]
    if PROJECTS[config.project].lava_fraction > 0:
        classes.append((UNKNOWN_CLASS, "lava"))
    fig, axes = plt.subplots(1, len(classes), figsize=(3.2 * len(classes), 2.8), dpi=100)
    bins = np.arange(MOVE_LIMIT + 3) - 0.5
    series = [
        ("no SRD", [o.untrained for o in outcomes], "tab:gray"),
        ("SRD", [o.srd for o in outcomes if o.srd is not None], "tab:red"),
    ]
    for ax, (cls, name) in zip(axes, classes, strict=True):
        for label, runs, colour in series:
            if runs:
                counts = np.concatenate([ev.tile_counts[:, cls] for ev in runs])
                ax.hist(
                    counts,
                    bins=bins,
                    cumulative=True,
                    density=True,
                    histtype="step",
                    color=colour,
                    label=label,
                )
        ax.set_title(f"{name} tiles traversed", fontsize=10)
        ax.set_xlabel("tiles")
        ax.set_xlim(-0.5, MOVE_LIMIT + 1)
    axes[0].set_ylabel("fraction of maps (cumulative)")
    axes[0].legend(loc="lower right")
    fig.suptitle(f"Project {config.project}, preset {config.preset}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def kernel_mosaic(weights: np.ndarray) -> np.ndarray:
    """(4, 5, 3, 3) kernels → one image, rows = DeconvSeqs, columns = layers, NaN gutters."""
    mosaic = np.full((4 * 4 - 1, 5 * 4 - 1), np.nan)
    for s in range(4):
        for layer in range(5):
            mosaic[4 * s : 4 * s + 3, 4 * layer : 4 * layer + 3] = weights[s, layer]
    return mosaic


def plot_weights(path: Path, panels: list[tuple[str, np.ndarray]]) -> None:
    """The 180 weights as heat maps, one panel per (title, (4, 5, 3, 3) kernels); red positive,
    blue negative, each panel on its own symmetric scale."""
    fig, axes = plt.subplots(
        1, len(panels), figsize=(3.6 * len(panels), 3.0), dpi=90, constrained_layout=True
    )
    for ax, (title, weights) in zip(np.atleast_1d(axes), panels, strict=True):
        limit = float(np.abs(weights).max())
        image = ax.imshow(kernel_mosaic(weights), cmap="bwr", vmin=-limit, vmax=limit)
        ax.set_title(title, fontsize=8)
        ax.set_xticks([4 * i + 1 for i in range(5)], [f"L{i + 1}" for i in range(5)], fontsize=7)
        ax.set_yticks([4 * i + 1 for i in range(4)], list(NAMED_INPUTS), fontsize=7)
        fig.colorbar(image, ax=ax, shrink=0.7)
    fig.suptitle(
        "Robot2NN DeconvSeq kernels (180 weights; rows: DeconvSeq, columns: layer)", fontsize=9
    )
    fig.savefig(path)
    plt.close(fig)


def trajectory_gif(path: Path, model: Robot2NN, one: Receptors, explore: torch.Tensor) -> None:
    """GIF of the executed plan on one map: the map with the robot (left) and v_Σ as the plan
    updates it (right; red positive, blue negative, white 0), one frame per move."""
    with torch.no_grad():
        v_sigma = model.v_sigma(one)
        plans: Plans = imagine(v_sigma, one, explore, model.rules)
    chosen = int(plans.executed(model.rules)[0])
    moves = int(plans.n_moves[0, chosen])
    w = v_sigma.shape[2]
    flat = plans.path[0, chosen, : moves + 1].numpy()
    xy = [(int(i % w), int(i // w)) for i in flat]
    values = v_sigma[0].numpy().copy()
    limit = float(np.abs(values).max())
    tiles = one.tile_class[0].numpy()
    colours = TILE_RGB[np.where(tiles == UNKNOWN_CLASS, LAVA, tiles)]
    heat = matplotlib.colormaps["bwr"]
    status = "reached" if bool(plans.reached[0, chosen]) else "not reached"
    caption = f"v_plan {float(plans.v_plan[0, chosen]):+.3f}, {status}"
    frames = []
    for k in range(moves + 1):
        if k > 0:
            left_x, left_y = xy[k - 1]
            values[left_y, left_x] = float(plans.left_values[0, chosen, k - 1])
        scores = (heat((values / limit + 1) / 2)[..., :3] * 255).astype(np.uint8)
        left, right = picture(colours, xy[: k + 1], 20), picture(scores, xy[: k + 1], 20)
        frame = Image.new("RGB", (2 * left.shape[1] + 10, left.shape[0] + 18), "white")
        frame.paste(Image.fromarray(left), (0, 18))
        frame.paste(Image.fromarray(right), (left.shape[1] + 10, 18))
        ImageDraw.Draw(frame).text((4, 3), f"move {k}/{moves}   {caption}", fill=(0, 0, 0))
        frames.append(frame.quantize(64, Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE))
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=350, loop=0)
