"""What the screener says about a manifest: accepted or not, and why, in plain words."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass(frozen=True)
class Reason:
    """One finding: which rule, about which neuron (e.g. ``"B"`` or ``"PG"``), in plain words."""

    rule: str
    neuron: str
    message: str

    def to_dict(self) -> dict[str, str]:
        """JSON form ``{rule, neuron, message}``."""
        return asdict(self)


@dataclass(frozen=True)
class Verdict:
    """The screener's decision on one manifest."""

    accepted: bool
    reasons: list[Reason] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON form ``{accepted, reasons: [{rule, neuron, message}]}``."""
        return {"accepted": self.accepted, "reasons": [r.to_dict() for r in self.reasons]}
