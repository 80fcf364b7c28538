"""Experiment kinds by name: what the CLI commands and the job backend (``POST /jobs``) run.

Each entry names a module, its config dataclass, its three unit functions (``sim.units``:
plan, compute one unit, assemble), and what a person reads first in its result. Modules are
imported only when the kind is used, so ``srd --help`` lists the kinds without importing any
simulation (nor torch).
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sim import units
from sim.experiment import ProgressFn, no_progress, parse_config
from sim.units import Decomposition, Payload, Unit, UnitRunner, plain


@dataclass(frozen=True)
class ExperimentKind:
    """Where the code of one experiment kind lives, and how its result reads."""

    name: str
    """The job kind and the CLI command."""
    module: str
    config: str
    """The config dataclass in ``module``: the options of the command and of the job."""
    planner: str
    """``module:function`` of ``plan(config) -> list[Unit]`` (see ``sim.units``)."""
    unit: str
    """``module:function`` of ``compute(config, unit, progress) -> Payload``."""
    assembler: str
    """``module:function`` of ``assemble(config, units, payloads, ...) -> dict``."""
    summary: str
    """One line for ``srd --help``: the first line of the config's docstring (a test checks)."""
    headline: tuple[str, ...] = ()
    """Result fields shown first by the command's human summary."""
    table: str | None = None
    """The result field holding a list of rows shown as a table, if any."""
    columns: tuple[str, ...] = ()
    """The columns of that table a person scans (those present in the rows)."""
    command: bool = True
    """Also an ``srd`` command (False: a job kind only)."""
    config_module: str | None = None
    """Where the config dataclass lives, if not in ``module``: a module that loads no
    simulation, so that the server checks a job's options and describes them without torch."""

    def config_class(self) -> type[Any]:
        """The config dataclass (imports its module only)."""
        module = importlib.import_module(self.config_module or self.module)
        config: type[Any] = getattr(module, self.config)
        return config

    def decomposition(self) -> Decomposition[Any]:
        """The kind's unit functions (imports their modules)."""
        return Decomposition(
            _function(self.planner), _function(self.unit), _function(self.assembler)
        )

    def load(self) -> tuple[type[Any], Callable[..., dict[str, Any]]]:
        """The config class and ``run(config, *, out_dir, progress) -> dict``: the units
        computed in this process."""
        return self.config_class(), functools.partial(units.run, self.decomposition())


def _function(reference: str) -> Any:
    """The function a ``module:name`` reference names."""
    module, name = reference.split(":")
    return getattr(importlib.import_module(module), name)


AUCTION_COLUMNS = (
    "setting",
    "rarity",
    "n_fish",
    "mean_price",
    "purchase_rate",
    "buyer_fraction",
    "revenue",
    "refused",
)
KINDS: dict[str, ExperimentKind] = {
    k.name: k
    for k in (
        ExperimentKind(
            "fish",
            "sim.fish",
            "FishConfig",
            "sim.fish:plan_fish",
            "sim.fish:compute_fish",
            "sim.fish:assemble_fish",
            "Robot fish 1D: FishNN on the ring tape, with or without SRD training.",
            headline=(
                "steps",
                "srd",
                "died",
                "meals",
                "mean_energy_first_1000",
                "mean_energy_last_1000",
            ),
            config_module="sim.configs",
        ),
        ExperimentKind(
            "lavaland",
            "sim.lavaland",
            "LavalandConfig",
            "sim.lavaland.experiment:plan_repeats",
            "sim.lavaland.experiment:compute_repeat",
            "sim.lavaland.experiment:assemble_repeats",
            "Robot2NN in lavaland: evaluate untrained, SRD-train one epoch, evaluate again.",
            headline=(
                "project",
                "preset",
                "eval_maps",
                "train_maps",
                "accuracy_untrained",
                "accuracy_srd",
                "lava_entered_untrained",
                "lava_entered_srd",
            ),
            table="repeats",
            columns=("repeat", "accuracy_untrained", "accuracy_srd", "lava_entered_srd"),
            config_module="sim.configs",
        ),
        ExperimentKind(
            "cheetah",
            "sim.cheetah",
            "CheetahConfig",
            "sim.cheetah.experiment:plan_cells",
            "sim.cheetah.experiment:compute_cells",
            "sim.cheetah.experiment:assemble_cells",
            "HalfCheetahSRD: the grid backswing × inhibitor × SRD (× learning rate) × trial.",
            headline=("n_runs", "steps", "video"),
            table="summary",
            columns=(
                "backswing",
                "inhibitor",
                "srd",
                "lr",
                "n",
                "mean_final_displacement",
                "sd_final_displacement",
            ),
            config_module="sim.configs",
        ),
        ExperimentKind(
            "auction-study",
            "studies.auctions",
            "StudyConfig",
            "studies.auctions:plan_auctions",
            "studies.auctions:compute_auctions",
            "studies.auctions:assemble_study",
            "Fish sale auctions without HTTP: purchase price and rate against item supply.",
            headline=("auctions", "refused", "buy_fraction"),
            table="rows",
            columns=AUCTION_COLUMNS,
            config_module="studies.config",
        ),
        ExperimentKind(
            "comparison",
            "studies.auctions",
            "ComparisonConfig",
            "studies.auctions:plan_auctions",
            "studies.auctions:compute_auctions",
            "studies.auctions:assemble_comparison",
            "Honest vs malicious: the same auctions with and without saboteurs, screened or not.",
            headline=("auctions", "buy_fraction"),
            table="rows",
            columns=AUCTION_COLUMNS,
            config_module="studies.config",
        ),
    )
}


def build_config(kind: str, params: dict[str, Any], *, stored: bool = False) -> Any:
    """Validate job ``params`` for ``kind`` into its config dataclass (raises ConfigError);
    ``stored``: a job's whole config, as it was stored once its params passed (every field is
    in it, none was given by the user: ``parse_config``'s ``given``)."""
    given: frozenset[str] | None = frozenset() if stored else None
    return parse_config(KINDS[kind].config_class(), params, given)


def run_kind(
    kind: str,
    config: Any,
    *,
    out_dir: Any,
    progress: ProgressFn,
    runner: UnitRunner | None = None,
) -> dict[str, Any]:
    """Run one experiment of ``kind``, its units computed by ``runner`` (default: in this
    process); returns its ``--json`` object."""
    return units.run(
        KINDS[kind].decomposition(), config, out_dir=out_dir, progress=progress, runner=runner
    )


def compute_unit(kind: str, params: dict[str, Any], unit: dict[str, Any]) -> Payload:
    """One unit of a ``kind`` experiment from JSON alone (the config's params and the unit's
    ``as_json``): what a cluster task runs. Returns the unit's plain payload."""
    config = build_config(kind, params, stored=True)
    decomposition = KINDS[kind].decomposition()
    payload: Payload = plain(decomposition.compute(config, Unit.from_json(unit), no_progress))
    return payload
