"""What a fine-tuning round may change in a model: its weights and biases, never its design
(activations, augmentation, settings, names). Plain data, no tensors: the server checks an
upload with it before anything is screened."""

from __future__ import annotations

from typing import Any

from agents.manifest import Manifest

FROZEN_IN_ROUNDS = "only weights and biases change in a fine-tuning round"


def round_update_problems(current: Manifest, update: Manifest) -> list[tuple[str, str]]:
    """What ``update`` changes beyond the weights and biases of ``current``, as (dotted path,
    message) pairs: a fine-tuning round moves the numbers, never the model's design
    (activations, augmentation, settings, names)."""
    return design_changes(current.model_dump(mode="json"), update.model_dump(mode="json"))


def design_changes(current: dict[str, Any], update: dict[str, Any]) -> list[tuple[str, str]]:
    """``round_update_problems`` on the manifests' JSON forms."""
    problems: list[tuple[str, str]] = []

    def walk(before: Any, after: Any, path: tuple[str, ...]) -> None:
        if path[-1:] == ("bias",) or path[-2:-1] == ("weights",):
            return
        if isinstance(before, dict) and isinstance(after, dict) and before.keys() == after.keys():
            for key in before:
                walk(before[key], after[key], (*path, key))
        elif before != after:
            problems.append((".".join(path), f"{FROZEN_IN_ROUNDS}: must stay {before!r}"))

    walk(current, update, ())
    return problems
