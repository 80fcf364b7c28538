"""The item rows an auction's patrons score: the prototype fish and its variations."""

from __future__ import annotations

import numpy as np

from agents.manifest import INPUTS
from agents.negotiator import BASE_ITEM
from sim.market.config import MarketConfig

SIZE_JITTER = 0.2
"""Rows 1..: length, weight and gill colour each get + U(−0.2, 0.2) (the reference's rows)."""
SUBTYPE_MINORITY = 0.2
"""Rows 1..: each sub-type flag is −½ with probability 0.2, else +½ (the reference's rows)."""
PRICE, BUY_FRACTION = INPUTS.index("price"), INPUTS.index("buy_fraction")
"""Columns of a row that the auction moves: the current price and the previous buy fraction f."""


def item_rows(config: MarketConfig, rng: np.random.Generator) -> np.ndarray:
    """The R item rows (the reference's): row 0 the design's base item at the config's base
    price; rows 1.. with jittered length, weight, gill and re-drawn sub-types. f starts at ½
    everywhere."""
    prototype = [BASE_ITEM[name] for name in INPUTS]
    prototype[PRICE] = config.base_price
    rows = np.tile(np.array(prototype, dtype=np.float64), (config.n_rows, 1))
    extra = config.n_rows - 1
    rows[1:, 1:4] += rng.uniform(-SIZE_JITTER, SIZE_JITTER, size=(extra, 3))
    rows[1:, 4:7] = np.where(rng.random((extra, 3)) < SUBTYPE_MINORITY, -0.5, 0.5)
    return rows
