"""Experiments as units: plain payloads, idempotent units, and results that do not depend on
the order in which units finish (what a cluster runner changes)."""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from sim import units
from sim.experiment import no_progress
from sim.units import Payload, Unit, UnitProgress, plain
from studies.registry import KINDS, build_config

SMALL = {
    "fish": {"steps": 300},
    "lavaland": {"eval_maps": 48, "train_maps": 24, "repeats": 3},
    "cheetah": {"backswing": [1, 5], "steps": 150, "trials": 20, "video": False},
    "auction-study": {"rarities": [0.3, 0.6], "trials": 3, "patrons": 16, "grid": True},
    "comparison": {"rarities": [0.5], "trials": 2, "patrons": 16},
}


def without_time(result: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in result.items() if k not in ("elapsed_s", "simulation_s")}


def files(folder: Path) -> dict[str, bytes]:
    """The CSV and JSON artifacts of a run (figures hold no numbers of their own)."""
    return {
        p.name: p.read_bytes()
        for p in sorted(folder.iterdir())
        if p.suffix in (".csv", ".json") and p.name != "summary.json"
    }


def test_plain_accepts_json_and_arrays_and_refuses_objects():
    good = {"a": [1, 2.5, None, "x", True], "b": np.zeros((2, 3)), "c": {"d": np.arange(3)}}
    assert plain(good) is good
    with pytest.raises(TypeError, match=r"payload\.model is a Linear"):
        plain({"model": torch.nn.Linear(2, 2)})
    with pytest.raises(TypeError, match=r"payload\.t\[0\] is a Tensor"):
        plain({"t": [torch.zeros(2)]})
    with pytest.raises(TypeError, match="int64"):
        plain({"n": np.int64(1)})  # numpy integers: convert them to Python numbers
    with pytest.raises(TypeError, match="key 1"):
        plain({1: 2})
    with pytest.raises(TypeError, match="ndarray"):
        plain({"o": np.array([object()])})


def reversed_runner(decomposition: Any, config: Any, seen: list[int]) -> units.UnitRunner:
    """Computes the units last first, as a cluster may finish them."""

    def runner(plan: Sequence[Unit], progress: UnitProgress) -> Iterator[tuple[int, Payload]]:
        for index in reversed(range(len(plan))):
            seen.append(index)
            unit = Unit.from_json(json.loads(json.dumps(plan[index].as_json())))
            yield index, decomposition.compute(config, unit, no_progress)

    return runner


@pytest.mark.parametrize("kind", sorted(SMALL))
def test_units_in_any_order_give_the_same_run(kind, tmp_path):
    torch.set_num_threads(1)
    config = build_config(kind, SMALL[kind])
    decomposition = KINDS[kind].decomposition()
    plan = decomposition.plan(config)
    assert plan == decomposition.plan(config)  # from the config alone
    if kind in ("lavaland", "cheetah", "auction-study"):
        assert len(plan) > 1, "the small config still has several units"
    reports: list[tuple[float, str]] = []
    here = units.run(
        decomposition,
        config,
        out_dir=tmp_path / "here",
        progress=lambda f, m: reports.append((f, m)),
    )
    fractions = [f for f, _ in reports]
    assert fractions == sorted(fractions) and fractions[0] >= 0 and fractions[-1] <= 1
    order: list[int] = []
    there = units.run(
        decomposition,
        config,
        out_dir=tmp_path / "there",
        runner=reversed_runner(decomposition, config, order),
    )
    assert order == list(reversed(range(len(plan))))
    assert without_time(there) == without_time(here)
    assert files(tmp_path / "there") == files(tmp_path / "here")


def test_a_unit_computed_twice_gives_the_same_payload():
    config = build_config("lavaland", SMALL["lavaland"])
    decomposition = KINDS["lavaland"].decomposition()
    unit = decomposition.plan(config)[1]
    first = decomposition.compute(config, unit, no_progress)
    again = decomposition.compute(config, unit, no_progress)
    assert first["untrained"]["reached"].dtype == bool
    for part in ("untrained", "srd"):
        for name, array in first[part].items():
            np.testing.assert_array_equal(array, again[part][name])
    np.testing.assert_array_equal(first["kernels"], again["kernels"])


def test_a_runner_that_loses_a_unit_fails_the_run(tmp_path):
    config = build_config("lavaland", {"eval_maps": 8, "train_maps": 0, "repeats": 2})
    decomposition = KINDS["lavaland"].decomposition()

    def loses_one(plan: Sequence[Unit], progress: UnitProgress) -> Iterator[tuple[int, Payload]]:
        yield 0, decomposition.compute(config, plan[0], no_progress)

    with pytest.raises(RuntimeError, match="1 of 2 units gave no payload"):
        units.run(decomposition, config, out_dir=tmp_path, runner=loses_one)
