"""Manifests as ``POST /submit`` takes them, and participant names no other test uses."""

from __future__ import annotations

import uuid
from typing import Any

import numpy as np

from agents.negotiator import honest_manifest, saboteur_manifest


def unique(prefix: str) -> str:
    """A participant name no other test uses."""
    return f"{prefix}-{uuid.uuid4().hex[:10]}"


def honest(name: str, seed: int = 0) -> dict[str, Any]:
    """An honest FSN manifest as JSON."""
    return honest_manifest(np.random.default_rng(seed), name).model_dump(mode="json")


def saboteur(name: str, seed: int = 0) -> dict[str, Any]:
    """An always-hold saboteur manifest as JSON."""
    return saboteur_manifest(np.random.default_rng(seed), name).model_dump(mode="json")
