"""What the engine reports of each iteration of each auction (``IterationRecord``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


@dataclass
class IterationRecord:
    """What happened in one iteration of one auction."""

    iteration: int
    price: float
    """Price at the start of the iteration (what the votes were about)."""
    n_available: int
    """Fish available at the start of the iteration."""
    votes: dict[str, int]
    """Row-0 decisions of the patrons active this round: {"buy", "hold", "quit"}."""
    row_votes: dict[str, int]
    """The same over every scored row (what feeds the f column)."""
    buyers: list[tuple[int, float]]
    """(patron index, purchase price) of this iteration's purchases."""
    quitters: list[int]
    """Patron indices that quit this iteration."""
    next_price: float
    n_available_after: int
    finished: bool
    stop_reason: str | None
    """sold_out | no_patrons | stalemate | max_iterations, once finished."""
    fine_tuned: list[int] = field(default_factory=list)
    """Patrons whose fine-tuned parameters were kept after this iteration."""
    reverted: list[int] = field(default_factory=list)
    """Patrons whose fine-tuned parameters the re-screening refused (reverted)."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        out = dataclasses.asdict(self)
        out["buyers"] = [{"patron": p, "price": price} for p, price in self.buyers]
        return out
