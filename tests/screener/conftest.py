"""Shared fixtures of the screener tests."""

from __future__ import annotations

import numpy as np
import pytest

from agents.manifest import Manifest
from agents.negotiator import honest_manifest


@pytest.fixture
def honest() -> Manifest:
    """One honest negotiator of the paper's randomisation (seeded)."""
    return honest_manifest(np.random.default_rng(7), "honest-7")
