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

With ``--per-supply``, it also asks whether a bar per supply in the market-impact test would
tell these models from honest ones: for every accepted model, and for every honest model of the
labelled corpus (seed 0) that the test judged and accepted, the worst supply's share of the
always-hold saboteurs' drop of the price over the test's 96 auctions (each supply's mean price
against the references' at that supply), as quantiles.

With ``--hold-near D``, the simulated server has a defence the real one does not: it holds a
submission the screener accepts when it lies within D (the largest change of one weight or
bias) of a submission of the same climb that was refused or held.

Run: ``.venv/bin/python benchmarks/screener_climb.py [--budget 50] [--seed 0] [--per-supply]
[--hold-near D]``.
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

from agents.manifest import Manifest, parse_manifest  # noqa: E402
from screener import impact, limits, review, screen_many  # noqa: E402

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
    the budget. With ``hold_near`` > 0, a defence the server does not have: a submission the
    screener accepts is held all the same when no weight or bias of it is ``hold_near`` or
    more from an earlier submission that was refused or held."""

    def __init__(self, budget: int, hold_near: float = 0.0) -> None:
        from server.config import Settings

        self.margin = Settings.model_fields["review_margin"].default
        self.left = budget
        self.hold_near = hold_near
        self.accepted: list[dict[str, Any]] = []
        self.refused: list[dict[str, Any]] = []

    def submit(self, manifest: dict[str, Any]) -> bool:
        self.left -= 1
        (verdict,) = screen_many([parse_manifest(manifest)])
        accepted = review(verdict, self.margin) == "accepted"
        if accepted and self.hold_near > 0:
            accepted = nearest_refused(manifest, self.refused) >= self.hold_near
        (self.accepted if accepted else self.refused).append(manifest)
        return accepted


def climb(
    honest: dict[str, Any], holder: dict[str, Any], budget: int, seed: int, hold_near: float = 0.0
) -> Server:
    """Both phases against one start; the server, holding every model it accepted."""
    rng = np.random.default_rng(seed)
    server = Server(budget, hold_near)
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


def worst_supply_shares(models: list[Manifest]) -> np.ndarray:
    """Each model's largest share, over the supplies, of the always-hold saboteurs' drop of
    the mean price, in the market-impact test's auctions of both stages."""
    trials = impact.first_trials() + impact.more_trials()
    refs = impact.wide_references()
    worst = []
    for outcome in impact.run(models, trials):
        shares = []
        for r in limits.IMPACT_SUPPLIES:
            alone, saboteurs = refs.alone.mean_price_at(r), refs.saboteurs.mean_price_at(r)
            mine = outcome.mean_price_at(r)
            if alone > saboteurs and not np.isnan(mine):
                shares.append((alone - mine) / (alone - saboteurs))
        worst.append(max(shares, default=np.nan))
    return np.array(worst)


def honest_tested() -> list[Manifest]:
    """The honest models of the labelled corpus (seed 0) that the market-impact test judged as
    submitted and accepted."""
    from tests.support.corpus import corpus

    honest = [entry.manifest for entry in corpus(0) if not entry.saboteur]
    found = []
    for start in range(0, len(honest), 64):
        chunk = honest[start : start + 64]
        for manifest, verdict in zip(chunk, screen_many(chunk), strict=True):
            judged = any(
                e.test == "market-impact" and e.detail.get("version") == "as submitted"
                for e in verdict.evidence
            )
            if judged and verdict.accepted:
                found.append(manifest)
    return found


def print_shares(label: str, shares: np.ndarray) -> None:
    median, tenth, top = np.nanquantile(shares, [0.5, 0.9, 1.0])
    print(
        f"{label:>34}: {len(shares):>4} models, worst supply's share median {median:.2f}, "
        f"90th percentile {tenth:.2f}, max {top:.2f}; above 0.8: {int((shares > 0.8).sum())}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--budget", type=int, default=50, help="submissions per start")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--starts", default=",".join(STARTS))
    parser.add_argument(
        "--hold-near",
        type=float,
        default=0.0,
        help="simulate holding what lies this near a refused or held submission",
    )
    parser.add_argument(
        "--per-supply", action="store_true", help="the worst supply's share, climbs vs honest"
    )
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
    climbed: list[dict[str, Any]] = []
    for name in args.starts.split(","):
        holder = json.loads((ROOT / "examples" / "red_team" / f"{name}.json").read_text())
        began = time.perf_counter()
        server = climb(honest, holder, args.budget, args.seed, args.hold_near)
        climbed += server.accepted
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
    if args.per_supply:
        print("per supply, over the market-impact test's 96 auctions:")
        print_shares(
            "accepted models of the climbs",
            worst_supply_shares([parse_manifest(m) for m in climbed]),
        )
        print_shares("honest models the test accepted", worst_supply_shares(honest_tested()))


if __name__ == "__main__":
    main()
