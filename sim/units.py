"""Experiments cut into independent units: the one way every kind is planned, computed and put
together, on this machine or on a cluster.

A kind's ``Decomposition`` has three functions:

* ``plan(config) -> list[Unit]``: the units, a function of the config alone (never of where
  they will run), each a small JSON spec with a label and a share of the work;
* ``compute(config, unit, progress) -> Payload``: one unit's numbers, a pure function of the
  config and the spec (seeded from them, no files written, no state kept between units), so a
  unit computed twice gives the same payload (a lost unit can simply run again);
* ``assemble(config, units, payloads, *, out_dir, progress, watch) -> dict``: the artifacts and
  the result from every unit's payload, in plan order.

A payload is plain data: JSON values and numpy arrays of numbers (``plain`` checks it), never a
model or any other object, so it crosses process and machine boundaries as numbers only.

``run`` computes the units with a ``UnitRunner``: ``in_process`` (one after another, here: the
CLI and the local job backend) or a cluster's (``server.jobs.ray_backend``). Every runner feeds
``assemble`` the same payloads, so local and cluster results are identical by construction.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

from sim.experiment import ProgressFn, Stopwatch, no_progress

C = TypeVar("C")
C_contra = TypeVar("C_contra", contravariant=True)

UNITS_SHARE = 0.95
"""Share of the progress bar given to the units (the rest: assembling the artifacts)."""

Payload = dict[str, Any]
"""One unit's numbers: JSON values and numpy arrays (see ``plain``)."""


@dataclass(frozen=True)
class Unit:
    """One independent piece of an experiment."""

    label: str
    """How progress messages name it (``repeat 2``, ``auctions 31-60``)."""
    spec: dict[str, Any] = field(default_factory=dict)
    """What to compute, as JSON (indices into the config's grid, a repeat number...)."""
    weight: float = 1.0
    """Its share of the experiment's work (progress counts finished weight)."""

    def as_json(self) -> dict[str, Any]:
        """The unit as a JSON object (what a cluster task receives)."""
        return asdict(self)

    @classmethod
    def from_json(cls, value: dict[str, Any]) -> Unit:
        """The unit ``as_json`` wrote."""
        return cls(str(value["label"]), dict(value["spec"]), float(value["weight"]))


class Assembler(Protocol[C_contra]):
    """``assemble(config, units, payloads, *, out_dir, progress, watch) -> result``."""

    def __call__(
        self,
        config: C_contra,
        units: Sequence[Unit],
        payloads: Sequence[Payload],
        *,
        out_dir: Path,
        progress: ProgressFn,
        watch: Stopwatch,
    ) -> dict[str, Any]: ...


@dataclass(frozen=True)
class Decomposition(Generic[C]):
    """A kind's three unit functions (see the module docstring)."""

    plan: Callable[[C], list[Unit]]
    compute: Callable[[C, Unit, ProgressFn], Payload]
    assemble: Assembler[C]


UnitProgress = Callable[[int, float, str], None]
"""Progress inside a unit: its index, the fraction of its work done, a message."""
UnitRunner = Callable[[Sequence[Unit], UnitProgress], Iterator[tuple[int, Payload]]]
"""Computes every unit, yielding (unit index, payload) as units finish, in any order.
In-process runners report progress inside a unit; cluster runners only as units end."""


def plain(value: Any, path: str = "payload") -> Any:
    """``value`` unchanged if it is plain data: dicts with string keys, lists, tuples, strings,
    booleans, integers, floats, None and numpy arrays of numbers or booleans; raises TypeError
    naming the first other thing found."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise TypeError(f"{path}: key {key!r} is not a string")
            plain(item, f"{path}.{key}")
        return value
    if isinstance(value, list | tuple):
        for index, item in enumerate(value):
            plain(item, f"{path}[{index}]")
        return value
    array = type(value).__module__ == "numpy" and type(value).__name__ == "ndarray"
    if array and value.dtype.kind in ("b", "i", "u", "f"):
        return value  # (this module does not import numpy: the command line reads it)
    raise TypeError(f"{path} is a {type(value).__name__}: units return JSON values and arrays")


def in_process(decomposition: Decomposition[Any], config: Any) -> UnitRunner:
    """The runner that computes the units one after another in this process."""

    def runner(units: Sequence[Unit], progress: UnitProgress) -> Iterator[tuple[int, Payload]]:
        for index, unit in enumerate(units):

            def report(fraction: float, message: str, index: int = index) -> None:
                progress(index, fraction, message)

            yield index, decomposition.compute(config, unit, report)

    return runner


def run(
    decomposition: Decomposition[C],
    config: C,
    *,
    out_dir: Path,
    progress: ProgressFn = no_progress,
    runner: UnitRunner | None = None,
) -> dict[str, Any]:
    """Plan the units, compute them with ``runner`` (default: ``in_process``), assemble."""
    watch = Stopwatch()
    units = decomposition.plan(config)
    total = sum(unit.weight for unit in units) or 1.0
    payloads: dict[int, Payload] = {}
    done = 0.0

    def inside(index: int, fraction: float, message: str) -> None:
        share = done + min(max(fraction, 0.0), 1.0) * units[index].weight
        progress(UNITS_SHARE * share / total, f"{units[index].label}: {message}")

    compute = runner or in_process(decomposition, config)
    for index, payload in compute(units, inside):
        if index in payloads:
            raise RuntimeError(f"unit {units[index].label} was computed twice")
        payloads[index] = plain(payload)
        done += units[index].weight
        progress(UNITS_SHARE * done / total, f"{len(payloads)}/{len(units)} units done")
    if len(payloads) != len(units):
        raise RuntimeError(f"{len(units) - len(payloads)} of {len(units)} units gave no payload")

    def assembling(fraction: float, message: str) -> None:
        progress(UNITS_SHARE + (1 - UNITS_SHARE) * fraction, message)

    ordered = [payloads[index] for index in range(len(units))]
    return decomposition.assemble(
        config, units, ordered, out_dir=out_dir, progress=assembling, watch=watch
    )
