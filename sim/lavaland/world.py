"""The one model of lavaland's world: tiles, maps, moves and what a robot observes.

Both the Gymnasium env (``sim.lavaland.env``) and the batched experiment use these functions:
maps are generated here, observed here (the robot registers exactly the env's observation), and
an executed plan is walked here to decide whether it reached the target.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

MAP_HEIGHT = 11
"""Rows H of a map (the reference's ``--map_size 11 13``)."""
MAP_WIDTH = 13
"""Columns W of a map."""
GRASS_FRACTION = 0.3
"""Probability g that a tile is grass."""
TARGET, DIRT, GRASS, LAVA = 0, 1, 2, 3
"""Tile ids (the order of the robot's recognised classes: lava is its unknown)."""
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
ACTION_STEPS = np.array([(1, 0), (0, 1), (-1, 0), (0, -1)], dtype=np.int64)
"""(dx, dy) of each action; x is the column, y the row."""


def generate_tiles(
    n: int,
    lava_fraction: float,
    grass_fraction: float = GRASS_FRACTION,
    *,
    rng: np.random.Generator,
    height: int = MAP_HEIGHT,
    width: int = MAP_WIDTH,
) -> tuple[np.ndarray, np.ndarray]:
    """n maps as tile ids (N, H, W) int8 and starts (N, 2) = (x, y), vectorised.

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


def self_one_hot(starts: np.ndarray, height: int, width: int) -> np.ndarray:
    """Positions (N, 2) = (x, y) → one-hot float32 (N, H, W)."""
    one_hot = np.zeros((len(starts), height, width), dtype=np.float32)
    one_hot[np.arange(len(starts)), starts[:, 1], starts[:, 0]] = 1.0
    return one_hot


@dataclass(frozen=True)
class Maps:
    """A batch of maps: tile ids and start positions."""

    tiles: np.ndarray
    """(N, H, W) int8 tile ids."""
    starts: np.ndarray
    """(N, 2) int64 start positions (x, y)."""

    def __len__(self) -> int:
        return len(self.tiles)

    def observe(self) -> tuple[np.ndarray, np.ndarray]:
        """What the robot observes at the start: RGB maps (N, 3, H, W) and one-hot self
        (N, H, W), both float32 (the env's ``map`` and ``self``)."""
        return tiles_to_rgb(self.tiles), self_one_hot(self.starts, *self.tiles.shape[1:])

    def select(self, index: int | slice) -> Maps:
        """Some of the maps (an int keeps a batch of one)."""
        rows = slice(index, index + 1) if isinstance(index, int) else index
        return Maps(self.tiles[rows], self.starts[rows])


def generate_maps(
    n: int,
    lava_fraction: float,
    grass_fraction: float = GRASS_FRACTION,
    *,
    rng: np.random.Generator,
) -> Maps:
    """n random 11×13 maps (see ``generate_tiles``)."""
    return Maps(*generate_tiles(n, lava_fraction, grass_fraction, rng=rng))


def move(positions: np.ndarray, actions: np.ndarray, height: int, width: int) -> np.ndarray:
    """Positions (..., 2) = (x, y) after actions (...): a move off the grid stays in place."""
    moved = positions + ACTION_STEPS[actions]
    inside = (
        (moved[..., 0] >= 0)
        & (moved[..., 0] < width)
        & (moved[..., 1] >= 0)
        & (moved[..., 1] < height)
    )
    return np.where(inside[..., None], moved, positions)


@dataclass(frozen=True)
class Walk:
    """Action sequences walked in the world, each stopping on the target."""

    reached_at: np.ndarray
    """(N,) the move that entered the target (1-based), 0 if it was never entered."""
    n_moves: np.ndarray
    """(N,) moves made."""
    tile_counts: np.ndarray
    """(N, 4) tile ids (target, dirt, grass, lava) of the start and every tile entered."""
    final: np.ndarray
    """(N, 2) final positions (x, y)."""


def walk(maps: Maps, actions: np.ndarray) -> Walk:
    """Walk each map's actions (N, T) from its start (−1 = no more moves); stop on the target."""
    n, height, width = maps.tiles.shape
    rows = np.arange(n)
    position = maps.starts.copy()
    counts = np.zeros((n, len(TILE_NAMES)), dtype=np.int64)
    counts[rows, maps.tiles[rows, position[:, 1], position[:, 0]]] += 1
    reached_at = np.zeros(n, dtype=np.int64)
    n_moves = np.zeros(n, dtype=np.int64)
    for k in range(actions.shape[1]):
        going = (actions[:, k] >= 0) & (reached_at == 0)
        if not going.any():
            break
        position = np.where(
            going[:, None], move(position, np.maximum(actions[:, k], 0), height, width), position
        )
        tile = maps.tiles[rows, position[:, 1], position[:, 0]]
        counts[rows[going], tile[going]] += 1
        n_moves += going
        reached_at = np.where(going & (tile == TARGET), k + 1, reached_at)
    return Walk(reached_at, n_moves, counts, position)


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
