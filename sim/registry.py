"""Experiment kinds by name: what the CLI commands and the job backend (``POST /jobs``) run.

Each entry names a module, its config dataclass and its ``run`` function; modules are imported
only when the kind is used, so a missing optional dependency fails that kind alone.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from sim.experiment import ProgressFn, parse_config


@dataclass(frozen=True)
class ExperimentKind:
    """Where the code of one experiment kind lives."""

    name: str
    module: str
    config: str
    runner: str

    def load(self) -> tuple[type[Any], Any]:
        """The config class and the run function (imports the module)."""
        mod = importlib.import_module(self.module)
        return getattr(mod, self.config), getattr(mod, self.runner)

    def available(self) -> bool:
        """True when the module and its run function exist."""
        try:
            self.load()
        except (ImportError, AttributeError):
            return False
        return True


KINDS: dict[str, ExperimentKind] = {
    k.name: k
    for k in (
        ExperimentKind("fish", "sim.fish", "FishConfig", "run"),
        ExperimentKind("lavaland", "sim.lavaland", "LavalandConfig", "run"),
        ExperimentKind("cheetah", "sim.cheetah", "CheetahConfig", "run"),
        ExperimentKind("auction-study", "sim.studies", "StudyConfig", "run_study"),
        ExperimentKind("comparison", "sim.studies", "ComparisonConfig", "run_comparison"),
    )
}


def build_config(kind: str, params: dict[str, Any]) -> Any:
    """Validate job ``params`` for ``kind`` into its config dataclass (raises ConfigError)."""
    config_cls, _ = KINDS[kind].load()
    return parse_config(config_cls, params)


def run_kind(kind: str, config: Any, *, out_dir: Any, progress: ProgressFn) -> dict[str, Any]:
    """Run one experiment of ``kind``; returns its ``--json`` object."""
    _, runner = KINDS[kind].load()
    result: dict[str, Any] = runner(config, out_dir=out_dir, progress=progress)
    return result
