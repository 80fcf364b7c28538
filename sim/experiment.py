"""Plumbing shared by every experiment: seeding, output folders, progress reports, configs.

Every experiment module exposes a config dataclass (one field per CLI option, each with a
one-line docstring) and ``run(config, *, out_dir, progress) -> dict`` whose return value is the
``--json`` object of the CLI and the ``result`` of a job. The CLI and the job backend are thin
callers of that function.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import random
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch
from pydantic import TypeAdapter, ValidationError

ProgressFn = Callable[[float, str], None]
"""Reports progress: a fraction in [0, 1] and a short human message."""

C = TypeVar("C")


def no_progress(fraction: float, message: str) -> None:
    """A progress callback that ignores its reports."""


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch global RNGs (experiments also keep their own generators)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def default_out_dir(command: str, seed: int, root: str | Path = "runs") -> Path:
    """``runs/<command>__<seed>__<unix time>/`` as in CleanRL."""
    return Path(root) / f"{command}__{seed}__{int(time.time())}"


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON (creating parent folders)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, sort_keys=False) + "\n")


def write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> str:
    """Write ``rows`` (dicts sharing their keys) as CSV with a header line, ``\\n`` line ends and
    empty cells for None; returns the file name. The one CSV writer of every experiment."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(
            handle, fieldnames=list(rows[0]) if rows else [], lineterminator="\n"
        )
        writer.writeheader()
        writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in rows)
    return path.name


def pyplot() -> Any:
    """matplotlib's pyplot on the file-only Agg backend, imported on first use (plots are the
    only part of an experiment that needs matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def split_csv(value: Any) -> Any:
    """Accept ``"0.1,0.5"`` as well as ``[0.1, 0.5]`` for multi-valued options."""
    if isinstance(value, str):
        return [part.strip() for part in value.split(",") if part.strip()]
    return value


class ConfigError(ValueError):
    """A config field is invalid; ``errors`` holds ``{"field": ..., "message": ...}`` items."""

    def __init__(self, errors: list[dict[str, str]]) -> None:
        self.errors = errors
        super().__init__("; ".join(f"{e['field']}: {e['message']}" for e in errors))


def parse_config(cls: type[C], params: dict[str, Any]) -> C:
    """Build the config dataclass ``cls`` from JSON ``params`` (job API), validating each field.

    Keys may use dashes or underscores (``train-maps`` or ``train_maps``); sequence fields also
    accept comma-separated strings. Unknown keys are refused, naming the key.
    """
    if not isinstance(params, dict):
        raise ConfigError([{"field": "params", "message": "must be a JSON object"}])
    names = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    clean: dict[str, Any] = {}
    errors: list[dict[str, str]] = []
    for key, value in params.items():
        name = key.replace("-", "_")
        if name not in names:
            errors.append({"field": key, "message": f"unknown option; known: {sorted(names)}"})
            continue
        origin = getattr(names[name].type, "__origin__", None)
        is_seq = origin in (tuple, list, Sequence) or str(names[name].type).startswith(
            ("tuple", "list")
        )
        clean[name] = split_csv(value) if is_seq else value
    if errors:
        raise ConfigError(errors)
    try:
        return TypeAdapter(cls).validate_python(clean)
    except ValidationError as exc:
        raise ConfigError(
            [
                {"field": ".".join(str(p) for p in err["loc"]) or "params", "message": err["msg"]}
                for err in exc.errors()
            ]
        ) from exc


def config_dict(config: Any) -> dict[str, Any]:
    """The config as a JSON-ready dict (tuples become lists)."""
    result: dict[str, Any] = json.loads(json.dumps(dataclasses.asdict(config)))
    return result


class Stopwatch:
    """Wall-clock timer: ``elapsed_s`` in the result objects."""

    def __init__(self) -> None:
        self.start = time.perf_counter()

    def elapsed(self) -> float:
        return round(time.perf_counter() - self.start, 3)
