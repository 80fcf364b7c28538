"""Write the quick start's population: six honest negotiators that differ (willingness to pay,
hold and quit leanings, fine-tuning settings) and one saboteur, as manifests beside this file.

    .venv/bin/python examples/population/make_population.py

The draws are seeded, so the files are always the same; a test checks that they are.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from agents.negotiator import honest_manifest, saboteur_manifest

SEED = 7
N_HONEST = 6
HERE = Path(__file__).resolve().parent


def population() -> dict[str, dict[str, Any]]:
    """File name → manifest (as JSON), in the order they are drawn."""
    rng = np.random.default_rng(SEED)
    files = {
        f"honest-{i}.json": honest_manifest(rng, f"honest-{i}").model_dump(mode="json")
        for i in range(1, N_HONEST + 1)
    }
    files["saboteur.json"] = saboteur_manifest(rng, "saboteur-1").model_dump(mode="json")
    return files


def text(manifest: dict[str, Any]) -> str:
    """A manifest file's exact text."""
    return json.dumps(manifest, indent=2) + "\n"


if __name__ == "__main__":
    for name, manifest in population().items():
        (HERE / name).write_text(text(manifest))
        print(f"wrote {HERE / name}")
