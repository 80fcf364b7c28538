"""Shared fixtures of the screener tests."""

from __future__ import annotations

import numpy as np
import pytest

from agents.manifest import Manifest
from agents.negotiator import honest_manifest
from screener import Verdict


@pytest.fixture
def honest() -> Manifest:
    """One honest negotiator of the paper's randomisation (seeded)."""
    return honest_manifest(np.random.default_rng(7), "honest-7")


def rules_of(verdict: Verdict) -> set[tuple[str, str]]:
    """The (rule, neuron) pairs of a verdict."""
    return {(r.rule, r.neuron) for r in verdict.reasons}


def message_of(verdict: Verdict, rule: str, neuron: str) -> str:
    """The message of the one reason with that rule and neuron."""
    (message,) = [r.message for r in verdict.reasons if (r.rule, r.neuron) == (rule, neuron)]
    return message
