"""``Lavaland-v0``: the lavaland world as a Gymnasium environment."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from agents.planning import MOVE_LIMIT
from sim.lavaland.world import (
    ACTION_NAMES,
    DIRT,
    GRASS_FRACTION,
    LAVA,
    MAP_HEIGHT,
    MAP_WIDTH,
    TARGET,
    TILE_NAMES,
    TILE_RGB,
    Maps,
    generate_tiles,
    move,
    parse_map,
    picture,
)


class Lavaland(gym.Env[dict[str, np.ndarray], int]):
    """A robot walks a grid of target, dirt, grass and lava tiles to the one target tile.

    **Map**: H × W tiles (default 11 × 13). Each episode draws a new map from ``np_random``:
    the start first (uniform), every tile dirt, then grass with probability ``grass_fraction``
    and lava with ``lava_fraction`` (i.i.d.), the target redrawn until it is not the start, the
    start forced to dirt. A fixed map can be given as strings (``map_rows`` or
    ``reset(options={"map": rows})``): "T" target, "." dirt, "g" grass, "L" lava, "S" start.

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
        self.map = Maps(np.full((1, height, width), DIRT, dtype=np.int8), np.zeros((1, 2), int))
        self.position = np.zeros(2, dtype=np.int64)
        self.moves = 0
        self.lava_entered = 0

    def _observation(self) -> dict[str, np.ndarray]:
        rgb, one_hot = Maps(self.map.tiles, self.position[None]).observe()
        return {"map": rgb[0], "self": one_hot[0]}

    def _tile(self) -> int:
        return int(self.map.tiles[0, self.position[1], self.position[0]])

    def _info(self) -> dict[str, Any]:
        return {
            "position": (int(self.position[0]), int(self.position[1])),
            "tile": TILE_NAMES[self._tile()],
            "moves": self.moves,
            "lava_entered": self.lava_entered,
            "reached": self._tile() == TARGET,
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        if options is not None and "map" in options:
            tiles, start = parse_map(options["map"])
            if tiles.shape != (self.height, self.width):
                raise ValueError(f"map must be {self.height}×{self.width}, got {tiles.shape}")
            self.map = Maps(tiles[None], np.array([start]))
        elif self.fixed is not None:
            self.map = Maps(self.fixed[0][None].copy(), np.array([self.fixed[1]]))
        else:
            self.map = Maps(
                *generate_tiles(
                    1,
                    self.lava_fraction,
                    self.grass_fraction,
                    rng=self.np_random,
                    height=self.height,
                    width=self.width,
                )
            )
        self.position = self.map.starts[0].copy()
        self.moves = 0
        self.lava_entered = 0
        return self._observation(), self._info()

    def step(self, action: int) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if not self.action_space.contains(action):
            raise ValueError(f"action must be 0-3 ({', '.join(ACTION_NAMES)}), got {action!r}")
        self.position = move(self.position, np.int64(action), self.height, self.width)
        self.moves += 1
        self.lava_entered += int(self._tile() == LAVA)
        reached = self._tile() == TARGET
        truncated = not reached and self.moves >= self.max_moves
        return self._observation(), float(reached), reached, truncated, self._info()

    def render(self) -> np.ndarray | None:
        """``rgb_array``: the map, 16 px per tile, the robot as a blue cross."""
        if self.render_mode != "rgb_array":
            return None
        return picture(TILE_RGB[self.map.tiles[0]], [self._info()["position"]])
