"""A ``MarketBatch``'s state after an iteration, as tensors and numbers (``state``) or bytes
(``dump``), and back: a batch built from the same manifests and configs continues from it bit
for bit."""

from __future__ import annotations

import io
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

if TYPE_CHECKING:
    from sim.market.engine import MarketBatch

CHECKPOINT_FORMAT = 2
"""``state`` format; 2 adds the pending remote rounds (1 is read as none)."""


def state(engine: MarketBatch) -> dict[str, Any]:
    """Everything needed to continue (tensors, numbers, generator states)."""
    return {
        "format": CHECKPOINT_FORMAT,
        "participants": engine.batch.participants.tolist(),
        "price": engine.price.tolist(),
        "threshold": engine.threshold.tolist(),
        "n_available": engine.n_available.tolist(),
        "iteration": engine.iteration.tolist(),
        "finished": engine.finished.tolist(),
        "stop_reason": list(engine.stop_reason),
        "active": torch.from_numpy(engine.active.copy()),
        "rows": engine.rows.clone(),
        # parameters move only by fine-tuning; otherwise they are the manifests' own
        "parameters": {k: v.clone() for k, v in engine.batch.parameters().items()}
        if any(c.fine_tune for c in engine.configs)
        else None,
        "accepted": None
        if engine.accepted is None
        else {k: v.clone() for k, v in engine.accepted.items()},
        "random": [r.state() for r in engine.random],
        "pending": engine.pending.tolist(),
    }


def load_state(engine: MarketBatch, saved: dict[str, Any]) -> None:
    """Continue ``engine`` from ``state`` of a batch built from the same manifests and
    configs."""
    if (
        saved.get("format") not in (1, CHECKPOINT_FORMAT)
        or saved["participants"] != engine.batch.participants.tolist()
    ):
        raise ValueError("checkpoint does not belong to these manifests")
    engine.price = np.array(saved["price"], dtype=np.float64)
    engine.threshold = np.array(saved["threshold"], dtype=np.float64)
    engine.n_available = np.array(saved["n_available"], dtype=np.int64)
    engine.iteration = np.array(saved["iteration"], dtype=np.int64)
    engine.finished = np.array(saved["finished"], dtype=bool)
    engine.stop_reason = list(saved["stop_reason"])
    engine.active = saved["active"].numpy().copy()
    engine.rows = saved["rows"].to(engine.rows.dtype).clone()
    if saved["parameters"] is not None:
        engine.replace_batch(
            engine.batch.with_parameters({k: v.clone() for k, v in saved["parameters"].items()})
        )
    if saved["accepted"] is not None:
        engine.accepted = {k: v.clone() for k, v in saved["accepted"].items()}
    for random, generators in zip(engine.random, saved["random"], strict=True):
        random.load(generators)
    engine.pending = np.array(saved.get("pending", [False] * engine.n_auctions), dtype=bool)


def dump(engine: MarketBatch) -> bytes:
    """``state`` as bytes (``load`` continues from them)."""
    buffer = io.BytesIO()
    torch.save(state(engine), buffer)
    return buffer.getvalue()


def load(engine: MarketBatch, blob: bytes) -> None:
    """Continue ``engine`` from ``dump`` of a batch built from the same manifests and configs."""
    load_state(engine, torch.load(io.BytesIO(blob), weights_only=True))
