"""An online climb on the screener's verdicts: how much harm can an accepted model do?

The attacker holds a model the screener refuses or holds (the red team's opening-window holders
a-d and the opening-price bargainer, ``examples/red_team/``) and an honest one
(``examples/honest.json``), and learns from each submission only what ``POST /submit``
answers. With ``--budget`` submissions per start (the quotas allow 60 refusals an hour from one
address):

1. bisection on t for the largest t the server accepts, where x(t) = honest + t (holder -
   honest) on every number of the manifest (integers rounded; the holder's flags);
2. the rest of the budget on pushes from the best accepted model towards the holder, by a
   random share (up to half) of what is left of the difference, every weight and bias also
   multiplied by (1 + 0.01 N(0, 1)); a push the server accepts becomes the best.

Every accepted model's harm is then measured by the red team's measure (``tests/support/
harm.py``, 8 trials per supply, seed 1: the share of the always-hold saboteur's drop of the
price, fine-tuning off / on), and the worst is printed beside the start's own harm, to compare
with the honest and sincere models of docs/screener.md; with, for each of the two worst, the
largest change of a weight or bias that separates it from the nearest model the server refused
or held in the same climb.

Run: ``.venv/bin/python benchmarks/screener_climb.py [--budget 50] [--seed 0]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from agents.manifest import parse_manifest  # noqa: E402
from screener import review, screen_many  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from screener_jitter import jittered  # noqa: E402

STARTS = (
    "opening-window-holder-a",
    "opening-window-holder-b",
    "opening-window-holder-c",
    "opening-window-holder-d",
    "opening-price-bargainer",
)
BISECTIONS = 8
"""Submissions of the first phase, after the holder itself."""
JITTER = 0.01
"""The relative jitter of every weight and bias in a push."""


def blend(honest: Any, holder: Any, t: float) -> Any:
    """honest + t (holder - honest) on every number (integers rounded, at least 1 where the
    honest and the holder's both are); anything else is the holder's."""
    if isinstance(holder, dict):
        return {key: blend(honest.get(key, value), value, t) for key, value in holder.items()}
    if isinstance(holder, list) and isinstance(honest, list) and len(honest) == len(holder):
        return [blend(h, v, t) for h, v in zip(honest, holder, strict=True)]
    if isinstance(holder, bool) or not isinstance(holder, int | float):
        return holder
    if not isinstance(honest, int | float) or isinstance(honest, bool):
        return holder
    value = honest + t * (holder - honest)
    if isinstance(holder, int) and isinstance(honest, int):
        return max(round(value), min(1, honest, holder))
    return value


class Server:
    """What ``POST /submit`` answers, at the default review margin: a submission costs one of
    the budget."""

    def __init__(self, budget: int) -> None:
        from server.config import Settings

        self.margin = Settings.model_fields["review_margin"].default
        self.left = budget
        self.accepted: list[dict[str, Any]] = []
        self.refused: list[dict[str, Any]] = []

    def submit(self, manifest: dict[str, Any]) -> bool:
        self.left -= 1
        (verdict,) = screen_many([parse_manifest(manifest)])
        accepted = review(verdict, self.margin) == "accepted"
        (self.accepted if accepted else self.refused).append(manifest)
        return accepted


def climb(honest: dict[str, Any], holder: dict[str, Any], budget: int, seed: int) -> Server:
    """Both phases against one start; the server, holding every model it accepted."""
    rng = np.random.default_rng(seed)
    server = Server(budget)
    if server.submit(holder):
        return server
    low, high = 0.0, 1.0  # x(low) accepted (the honest model), x(high) not
    best = blend(honest, holder, 0.0)
    for _ in range(min(BISECTIONS, server.left)):
        middle = (low + high) / 2
        candidate = blend(honest, holder, middle)
        if server.submit(candidate):
            low, best = middle, candidate
        else:
            high = middle
    while server.left > 0:
        candidate = jittered(blend(best, holder, rng.uniform(0.0, 0.5)), JITTER, rng)
        if server.submit(candidate):
            best = candidate
    return server


def worst_harm(models: list[dict[str, Any]]) -> tuple[float, float, int, int]:
    """The largest harm of ``models`` with fine-tuning off and on, and which model each is."""
    from tests.support.harm import harms, saboteur_harm

    found, _ = harms([parse_manifest(m) for m in models], 8, 1)
    reference = saboteur_harm(8, 1)
    fractions = [h.fraction(reference) for h in found]
    off = max(range(len(fractions)), key=lambda i: fractions[i][0])
    on = max(range(len(fractions)), key=lambda i: fractions[i][1])
    return fractions[off][0], fractions[on][1], off, on


def numbers(manifest: dict[str, Any]) -> np.ndarray:
    """A manifest's weights and biases, in a fixed order."""
    found: list[float] = []

    def walk(node: Any) -> None:
        if isinstance(node, dict):
            for key in sorted(node):
                value = node[key]
                if key == "weights" and isinstance(value, dict):
                    found.extend(float(value[name]) for name in sorted(value))
                elif key == "bias" and isinstance(value, int | float):
                    found.append(float(value))
                else:
                    walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(manifest)
    return np.array(found)


def nearest_refused(model: dict[str, Any], refused: list[dict[str, Any]]) -> float:
    """The largest change of a weight or bias from ``model`` to the nearest model the server
    refused or held in the same climb."""
    here = numbers(model)
    return min((float(np.abs(numbers(other) - here).max()) for other in refused), default=np.inf)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--budget", type=int, default=50, help="submissions per start")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--starts", default=",".join(STARTS))
    args = parser.parse_args()

    import torch

    torch.set_num_threads(1)
    honest = json.loads((ROOT / "examples" / "honest.json").read_text())
    print(
        f"{args.budget} submissions per start, seed {args.seed}; harm: share of the always-hold "
        "saboteur's, fine-tuning off / on (8 trials, seed 1)"
    )
    honest_off, honest_on, _, _ = worst_harm([honest])
    print(f"the honest model's own harm: {honest_off:.2f} / {honest_on:.2f}")
    print(
        f"{'start':>26} {'own harm':>13} {'accepted':>9} {'worst accepted off / on':>24} "
        f"{'nearest refused':>16}"
    )
    for name in args.starts.split(","):
        holder = json.loads((ROOT / "examples" / "red_team" / f"{name}.json").read_text())
        began = time.perf_counter()
        server = climb(honest, holder, args.budget, args.seed)
        own_off, own_on, _, _ = worst_harm([holder])
        worst, near = "-", "-"
        if server.accepted:
            off, on, at_off, at_on = worst_harm(server.accepted)
            worst = f"{off:.2f} / {on:.2f}"
            gaps = [nearest_refused(server.accepted[i], server.refused) for i in (at_off, at_on)]
            near = " / ".join(f"{gap:.3f}" for gap in gaps)
        print(
            f"{name:>26} {own_off:>6.2f} / {own_on:<4.2f} {len(server.accepted):>9} "
            f"{worst:>24} {near:>16}  ({time.perf_counter() - began:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
