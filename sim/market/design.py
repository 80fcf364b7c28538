"""What a fine-tuning round may change in a model: its weights and biases, never its design
(activations, augmentation, settings, names). Plain data, no tensors: the server checks an
upload with it before anything is screened."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

from agents.manifest import Manifest

FROZEN_IN_ROUNDS = "only weights and biases change in a fine-tuning round"
FROZEN_JUDGE = "the judge is frozen (pfc.trainable is false): fine-tuning never moves it"
NUMBERS = ("weights", "bias")
"""The fields a fine-tuning round moves, wherever a neuron has them."""

Design = dict[str, Any]
"""A manifest's JSON form without its weights and biases (``design``)."""


def _numbers_of(model: type[BaseModel]) -> dict[str, Any]:
    """pydantic's ``exclude`` spec of every weights and bias field under ``model``."""
    spec: dict[str, Any] = {}
    for name, field in model.model_fields.items():
        if name in NUMBERS:
            spec[name] = True
        elif isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            inner = _numbers_of(field.annotation)
            if inner:
                spec[name] = inner
    return spec


_NUMBERS = _numbers_of(Manifest)


def design(manifest: Manifest) -> Design:
    """Everything a fine-tuning round must leave as it is (one dump, weights and biases left
    out by pydantic): two manifests may stand for one another in a round exactly when their
    designs are equal."""
    return manifest.model_dump(mode="json", exclude=_NUMBERS)


def round_update_problems(
    current: Manifest, update: Manifest, *, current_design: Design | None = None
) -> list[tuple[str, str]]:
    """What ``update`` changes beyond the weights and biases of ``current``, as (dotted path,
    message) pairs: a fine-tuning round moves the numbers, never the model's design
    (activations, augmentation, settings, names). ``current_design``, if given, is
    ``design(current)`` computed earlier."""
    if (design(current) if current_design is None else current_design) == design(update) and (
        current.pfc.trainable or current.pfc == update.pfc
    ):
        return []
    return design_changes(current.model_dump(mode="json"), update.model_dump(mode="json"))


def design_changes(current: dict[str, Any], update: dict[str, Any]) -> list[tuple[str, str]]:
    """``round_update_problems`` on the manifests' JSON forms. A frozen judge
    (``pfc.trainable`` false) keeps its weights and biases too: fine-tuning never moves them,
    so an update that does is not a fine-tuned version of ``current``."""
    problems: list[tuple[str, str]] = []
    judge_frozen = current.get("pfc", {}).get("trainable") is False

    def walk(before: Any, after: Any, path: tuple[str, ...]) -> None:
        numbers = path[-1:] == ("bias",) or path[-2:-1] == ("weights",)
        if numbers and path[:1] == ("pfc",) and judge_frozen:
            if before != after:
                problems.append((".".join(path), f"{FROZEN_JUDGE}: must stay {before!r}"))
            return
        if numbers:
            return
        if isinstance(before, dict) and isinstance(after, dict) and before.keys() == after.keys():
            if before == after:  # nothing below differs (compared in C, not walked)
                return
            for key in before:
                walk(before[key], after[key], (*path, key))
        elif before != after:
            problems.append((".".join(path), f"{FROZEN_IN_ROUNDS}: must stay {before!r}"))

    walk(current, update, ())
    return problems
