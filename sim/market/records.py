"""What the engine reports of each iteration of each auction (``IterationRecord``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class VoteExplanation:
    """Why one patron voted as it did on row 0 (the row that decides): its named neurons
    there, each averaged over the patron's D_ic copies as its vote was."""

    patron: int
    """The patron's position in the auction."""
    vote: str
    """buy | hold | quit."""
    sensor: dict[str, float]
    """The external sensor after its activations: PG, SZ, LSR, ST."""
    decision: dict[str, float]
    """The decision logits B, L, Q (the vote is the largest)."""
    judgement: dict[str, float]
    """The prefrontal cortex's judgements PGL (holding at a high price), BC (buying cheap)
    and FQ (quitting a good fish), read from the softmax of the sensor and the decision,
    before their tanh."""
    pfc: dict[str, float]
    """The prefrontal cortex's verdicts T (right) and F (wrong) on that decision."""


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
    refusals: list[list[dict[str, str]]] = field(default_factory=list, compare=False)
    """Why, for each of ``reverted`` in order: the screener's reasons, each ``{rule, neuron,
    message}`` (empty when the re-screening gave none). The judge's words, not the market's
    numbers: not part of the record's equality nor of ``to_dict``."""
    row: dict[str, float] = field(default_factory=dict, compare=False)
    """The inputs of row 0 the patrons voted on, by name (empty unless explained)."""
    explanations: list[VoteExplanation] = field(default_factory=list, compare=False)
    """Each voter's explanation, in patron order (empty unless the market explains). Derived
    from the votes, so not part of the record's equality nor of ``to_dict``."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form of what happened (without the explanations and the refusals'
        reasons)."""
        out = dataclasses.asdict(self)
        del out["row"], out["explanations"], out["refusals"]
        out["buyers"] = [{"patron": p, "price": price} for p, price in self.buyers]
        return out

    def explained(self) -> dict[str, Any]:
        """The explanations, JSON-ready: ``{row, patrons: [{patron, vote, sensor, decision,
        judgement, pfc}]}``."""
        patrons = [
            {
                "patron": e.patron,
                "vote": e.vote,
                "sensor": dict(e.sensor),
                "decision": dict(e.decision),
                "judgement": dict(e.judgement),
                "pfc": dict(e.pfc),
            }
            for e in self.explanations
        ]
        return {"row": self.row, "patrons": patrons}
