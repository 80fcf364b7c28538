"""What a remote agent does in a fine-tuning round: the round as it receives it
(``RoundInfo``) and its fine-tuner, ``faithful_fine_tune`` (what the server itself would do) or
``always_hold`` (a saboteur's bait-and-switch)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np

from agents.manifest import Manifest
from agents.negotiator import saboteur_manifest


@dataclass(frozen=True)
class RoundInfo:
    """One fine-tuning round as the agent receives it."""

    auction_id: int
    round: int
    iteration: int
    rows: np.ndarray
    """(R, 8) float64: p, l, w, g, st1, st2, st3, f of every item row."""
    fine_tune_seed: int
    augmentation_seed: int
    deadline: datetime
    seconds_left: float
    position: int
    """The agent's patron position in the auction (its seeds depend on it)."""

    @classmethod
    def from_state(cls, state: dict[str, Any], position: int) -> RoundInfo:
        """The round from the JSON of ``GET /auctions/{id}/rounds/current`` (an open round)."""
        return cls(
            auction_id=int(state["auction_id"]),
            round=int(state["round"]),
            iteration=int(state["iteration"]),
            rows=np.array(state["rows"], dtype=np.float64).reshape(-1, 8),
            fine_tune_seed=int(state["fine_tune_seed"]),
            augmentation_seed=int(state["augmentation_seed"]),
            deadline=datetime.fromisoformat(state["deadline"]),
            seconds_left=float(state["seconds_left"]),
            position=position,
        )


FineTuner = Callable[[Manifest, RoundInfo], Manifest]
"""The participant's own fine-tuning: current manifest and round → the manifest to upload
(weights and biases may change, nothing else)."""


def faithful_fine_tune(manifest: Manifest, info: RoundInfo) -> Manifest:
    """SRD fine-tuning of this one model exactly as the server would run it: the manifest's
    own epochs, batch size and learning rate, the round's rows and seeds, the patron's
    position."""
    if manifest.fine_tuning.epochs == 0:
        return manifest
    import torch  # on first use: a command that only checks its options never loads it

    from agents.batch import from_manifests, to_manifest
    from agents.fine_tuning import fine_tune_round

    tuned = fine_tune_round(
        from_manifests([manifest]),
        torch.from_numpy(info.rows),
        np.array([info.fine_tune_seed], dtype=np.uint64),
        np.array([info.augmentation_seed], dtype=np.uint64),
        np.array([info.position]),
    )
    return to_manifest(tuned, 0)


def always_hold(manifest: Manifest, info: RoundInfo) -> Manifest:
    """The bait-and-switch: the admitted model's design with a saboteur's always-hold weights
    and biases (buy neuron inert, hold bias +5), whatever the round says."""
    switched = saboteur_manifest(np.random.default_rng(info.round), manifest.participant)
    data = switched.model_dump(mode="json")
    kept = manifest.model_dump(mode="json")
    for name in ("participant", "description", "augmentation", "fine_tuning"):
        data[name] = kept[name]
    data["pfc"]["trainable"] = kept["pfc"]["trainable"]
    for name, neuron in data["external_sensor"].items():
        neuron["activation"] = kept["external_sensor"][name]["activation"]
    return Manifest.model_validate(data)
