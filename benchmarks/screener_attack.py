"""Red team against the screener: the most harmful model it admits.

Harm is the drop of the mean purchase price when 32 copies of a model join 32 honest patrons,
against the same auctions without them, at supplies 0.1 to 0.4, with fine-tuning off and on
(``tests/support/harm.py``), as a fraction of the always-hold saboteur's drop. The search
maximises max(fraction off, fraction on) over models ``screener.screen`` accepts:

* hand-built families (``tests/support/disguised.py``: ``DISGUISED``): a random start among
  ``--draws`` accepted draws of the family's numbers, then a (1+λ) evolution strategy over them;
* a (1+λ) evolution strategy over every numeric field of the manifest (weights, biases,
  activation parameters, augmentation, fine-tuning), started from the honest example and from
  the always-hold saboteur (refused at first: while refused, the fitness is minus the number of
  reasons, which leads the search into the accepted region).

Each generation's accepted offspring run in one lock-step batch of harm auctions with few trials
(``--trials``); the best model of every search is measured again with ``--final-trials``. The
found models are written to ``--out`` (manifest JSON per search) to extend the labelled corpus.

``--noise-gated`` runs one search only, over the noise-gated holder family
(``tests/support/red_team_noise.py``: an ST peak narrower than the model's own augmentation noise,
so the clean probes see a sincere bidder and the market a holder), each candidate scored by its
harm in the market's auctions, where every vote is evaluated on its noisy copies; the report
says for the best model whether it holds on the clean scan and on the noisy one.

``--stayers`` searches only among the models that do not quit at the opening price (the base
fish at 5.00 with the opening buy fraction ½, augmentation off): a model that quits there leaves
the auction at its first vote, as a sincere low bidder does, and its only effect on the others is
that opening vote (the buy fraction of the first round counts every voter). Such models are
still admitted and still scored, but they do not count as a find.

Run: ``.venv/bin/python benchmarks/screener_attack.py [--generations 20] [--lam 8]
[--trials 3] [--final-trials 8] [--seed 0] [--out build/screener_attack] [--stayers]
[--noise-gated]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from agents.batch import from_manifests
from agents.manifest import Manifest
from screener import screen_many
from screener.checks import cheap_checks
from tests.support.disguised import DISGUISED, Family
from tests.support.harm import (
    OPENING_VOTES,
    SUPPLIES,
    Harm,
    harms,
    opening_votes,
    saboteur,
    saboteur_harm,
)
from tests.support.red_team_noise import NoiseGatedFamily

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
BOUNDS: dict[str, tuple[float, float]] = {
    "a": (1e-3, 1000.0),
    "c": (-1000.0, 1000.0),
    "negative_slope": (0.0, 1.0),
    "epsilon": (1e-9, 1.0),
    "copies": (1, 16),
    "noise_std": (0.0, 1.0),
    "epochs": (0, 10),
    "batch_size": (1, 64),
    "learning_rate": (0.0, 1.0),
}
"""The schema's bounds of the numbers that have one (weights and biases have none)."""
LOG_FIELDS = ("epsilon", "learning_rate", "a")
INTEGER_FIELDS = ("copies", "epochs", "batch_size")


def numeric_fields(manifest: Manifest) -> list[tuple[str, float]]:
    """Every numeric field of a manifest (dotted path, value), in a fixed order."""
    out: list[tuple[str, float]] = []

    def walk(node: Any, path: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                walk(value, f"{path}.{key}" if path else key)
        elif isinstance(node, bool):
            return
        elif isinstance(node, int | float) and path != "schema_version":
            out.append((path, float(node)))

    walk(manifest.model_dump(mode="json"), "")
    return out


def with_fields(manifest: Manifest, values: dict[str, float]) -> Manifest | None:
    """The manifest with some numeric fields replaced (None if the schema refuses them)."""
    data = manifest.model_dump(mode="json")
    for path, value in values.items():
        *head, last = path.split(".")
        node = data
        for key in head:
            node = node[key]
        node[last] = round(value) if last in INTEGER_FIELDS else float(value)
    try:
        return Manifest.model_validate(data)
    except ValueError:
        return None


@dataclass
class Scored:
    """A model, whether the screener accepts it, and its measured harm (if accepted)."""

    manifest: Manifest
    accepted: bool
    reasons: int
    eligible: bool = True
    """Counts as a find (with ``--stayers``: does not quit at the opening price)."""
    harm: Harm | None = None
    evaluations: int = 0
    total: float = 0.0

    @property
    def fitness(self) -> float:
        """Harm fraction (worst setting), averaged over evaluations; −(1 + reasons) if refused,
        −½ if admitted but not eligible."""
        if not self.accepted:
            return -1.0 - self.reasons
        if not self.eligible:
            return -0.5
        return self.total / max(self.evaluations, 1)


def worst_fraction(harm: Harm, reference: Harm) -> float:
    return max(harm.fraction(reference))


def score(
    models: Sequence[Manifest], trials: int, seed: int, stayers: bool = False
) -> list[Scored]:
    """Screen the models, measure the harm of the accepted eligible ones (one batch); with
    ``stayers``, a model that quits at the opening price is not eligible."""
    if not models:
        return []
    verdicts = screen_many(list(models))
    quits = opening_votes(models) == 2
    scored = [
        Scored(m, v.accepted, len(v.reasons), eligible=not (stayers and q))
        for m, v, q in zip(models, verdicts, quits, strict=True)
    ]
    evaluate([s for s in scored if s.accepted and s.eligible], trials, seed)
    return scored


def evaluate(scored: Sequence[Scored], trials: int, seed: int) -> None:
    """Measure (again) the harm of accepted models; fitness is the mean over measurements."""
    if not scored:
        return
    reference = saboteur_harm(trials, seed)
    found, _ = harms([s.manifest for s in scored], trials, seed)
    for s, harm in zip(scored, found, strict=True):
        s.harm = harm
        s.evaluations += 1
        s.total += worst_fraction(harm, reference)


def evolve(
    start: Scored,
    mutate: Callable[[Scored, np.random.Generator, float], Manifest | None],
    generations: int,
    lam: int,
    trials: int,
    rng: np.random.Generator,
    seed: int,
    log: Callable[[str], None],
    stayers: bool = False,
) -> Scored:
    """(1+λ) evolution strategy with the 1/5 success rule on the step size; the parent is
    measured again every generation (its fitness is a running mean, so a lucky draw of the
    few-trial harm does not freeze the search)."""
    parent, sigma = start, 0.3
    for g in range(generations):
        children = [m for m in (mutate(parent, rng, sigma) for _ in range(lam)) if m is not None]
        scored = score(children, trials, seed, stayers)
        if parent.accepted and parent.eligible:
            evaluate([parent], trials, seed)
        if parent.accepted and parent.eligible:
            better = [c for c in scored if c.fitness > parent.fitness]
            sigma *= np.exp((len(better) / max(len(scored), 1) - 0.2) / 0.8)
            sigma = float(np.clip(sigma, 0.02, 1.0))
        else:  # still refused (or not eligible): drift among equals, at a constant step
            better = [c for c in scored if c.fitness >= parent.fitness]
        if better:
            parent = max(better, key=lambda c: c.fitness)
        log(f"    gen {g:2d}: fitness {parent.fitness:+.3f} σ {sigma:.2f} accepted "
            f"{sum(c.accepted for c in scored)}/{len(scored)}")  # fmt: skip
    return parent


def field_mutation(base: Manifest) -> Callable[[Scored, np.random.Generator, float], Manifest]:
    """Mutation over every numeric field: a few fields at a time, each by σ times its scale."""

    def mutate(parent: Scored, rng: np.random.Generator, sigma: float) -> Manifest | None:
        fields = numeric_fields(parent.manifest)
        changes: dict[str, float] = {}
        for i in rng.choice(len(fields), size=1 + rng.poisson(2), replace=False):
            path, value = fields[int(i)]
            name = path.rsplit(".", 1)[-1]
            low, high = BOUNDS.get(name, (-np.inf, np.inf))
            if name in LOG_FIELDS and value > 0:
                new = value * float(np.exp(sigma * 2.0 * rng.normal()))
            else:
                new = value + sigma * max(abs(value), 0.1) * float(rng.normal())
            if name in INTEGER_FIELDS:
                new = value + float(np.sign(new - value) * max(1, round(abs(new - value))))
            changes[path] = float(np.clip(new, low, high))
        return with_fields(parent.manifest, changes)

    return mutate


def family_mutation(
    family: Family | NoiseGatedFamily, base: Manifest
) -> Callable[..., Manifest | None]:
    """Mutation of a family's numbers (positions in [0, 1]); the position is kept in the
    description so that the child knows it."""

    def mutate(parent: Scored, rng: np.random.Generator, sigma: float) -> Manifest | None:
        u = np.array(json.loads(parent.manifest.description))
        child = np.clip(u + sigma * 0.3 * rng.normal(size=len(u)), 0, 1)
        return _family_model(family, base, child)

    return mutate


def _family_model(
    family: Family | NoiseGatedFamily, base: Manifest, u: np.ndarray
) -> Manifest | None:
    try:
        model = family.build(base, u)
    except ValueError:
        return None
    return model.model_copy(update={"description": json.dumps([round(float(x), 6) for x in u])})


def run(args: argparse.Namespace) -> None:
    rng = np.random.default_rng(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    honest = Manifest.model_validate_json((EXAMPLES / "honest.json").read_text())
    reference = saboteur_harm(args.final_trials, args.seed)
    print(
        f"always-hold saboteur, {args.final_trials} trials: price drop "
        f"{reference.price[0]:.4f} (fine-tuning off), {reference.price[1]:.4f} (on); unsold "
        f"{reference.unsold[0]:+.2f} / {reference.unsold[1]:+.2f} fish per auction"
    )
    searches: list[tuple[str, Scored]] = []
    start_time = time.perf_counter()

    def log(line: str) -> None:
        if args.verbose:
            print(line)

    families: tuple[Family | NoiseGatedFamily, ...] = (
        (NoiseGatedFamily(),) if args.noise_gated else DISGUISED
    )
    for family in families:
        draws = [_family_model(family, honest, rng.random(len(family.params)))
                 for _ in range(args.draws)]  # fmt: skip
        scored = score([d for d in draws if d is not None], args.trials, args.seed, args.stayers)
        accepted = [s for s in scored if s.accepted and s.eligible]
        start = max(accepted or scored, key=lambda s: s.fitness)
        print(f"{family.name}: {len(accepted)}/{len(scored)} random draws accepted; "
              f"best start {start.fitness:+.3f}")  # fmt: skip
        best = evolve(start, family_mutation(family, honest), args.generations, args.lam,
                      args.trials, rng, args.seed, log, args.stayers)  # fmt: skip
        searches.append((f"family:{family.name}", best))
    starts = (
        ()
        if args.noise_gated
        else (("honest example", honest), ("always-hold saboteur", saboteur()))
    )
    for name, start_model in starts:
        (start,) = score([start_model], args.trials, args.seed, args.stayers)
        print(f"all fields from the {name}: start fitness {start.fitness:+.3f}")
        best = evolve(start, field_mutation(start_model), args.generations * 2, args.lam,
                      args.trials, rng, args.seed, log, args.stayers)  # fmt: skip
        searches.append((f"fields:{name}", best))
    print(f"\nsearch took {time.perf_counter() - start_time:.0f} s")
    report(searches, args, reference, out)


def report(
    searches: list[tuple[str, Scored]], args: argparse.Namespace, reference: Harm, out: Path
) -> None:
    """Measure every search's best admitted model again with more trials; print the table and
    write the models. A model that never holds on the reachable decisive row is marked
    'quitter'; its opening vote is shown beside (a model that quits at the opening price harms
    only through that vote, as a sincere low bidder does)."""
    admitted = [(name, s) for name, s in searches if s.accepted]
    found, outcomes = harms([s.manifest for _, s in admitted], args.final_trials, args.seed)
    models = [s.manifest for _, s in admitted]
    cheap = cheap_checks(from_manifests(models)) if admitted else None
    holds = cheap.holds if cheap is not None else []
    votes = opening_votes(models) if admitted else []
    print(f"\nbest admitted model per search, {args.final_trials} trials; harm = price drop as a "
          "fraction of the always-hold saboteur's (fine-tuning off / on)")  # fmt: skip
    print(f"{'search':38} {'kind':8} {'opening':7} {'off':>7} {'on':>7}   mean price alone → "
          f"with, per supply {', '.join(f'{r:g}' for r in SUPPLIES)} (off | on)")  # fmt: skip
    index = {name: c for c, (name, _) in enumerate(admitted)}
    worst = {
        "holder": float("-inf"),
        "holder (only on its noisy copies)": float("-inf"),
        "quitter": float("-inf"),
    }
    past = {
        "stays past the opening vote": float("-inf"),
        "quits at the opening price": float("-inf"),
    }
    for name, s in searches:
        path = out / (name.replace(":", "_").replace(" ", "-") + ".json")
        path.write_text(s.manifest.model_dump_json(indent=2) + "\n")
        if not s.accepted:
            print(f"{name:38} {'-':8} {'-':7} {'refused':>7} {'refused':>7}   (no accepted "
                  "model found)")  # fmt: skip
            continue
        c = index[name]
        kind = "holder" if holds[c] else "quitter"
        if cheap is not None and cheap.noisy.holds[c] and not cheap.probed.holds[c]:
            kind = "holder (only on its noisy copies)"
        opening = OPENING_VOTES[int(votes[c])]
        off, on = found[c].fraction(reference)
        worst[kind] = max(worst[kind], off, on)
        group = (
            "quits at the opening price" if opening == "quits" else "stays past the opening vote"
        )
        past[group] = max(past[group], off, on)
        cells = [
            " ".join(
                f"{outcomes[(-1, fine_tune, r)].mean_price:.3f}→"
                f"{outcomes[(c, fine_tune, r)].mean_price:.3f}"
                for r in SUPPLIES
            )
            for fine_tune in (False, True)
        ]
        print(f"{name:38} {kind:8} {opening:7} {off:7.3f} {on:7.3f}   {cells[0]} | {cells[1]}")
    for kind, value in [*worst.items(), *past.items()]:
        shown = "none admitted" if value == float("-inf") else f"{value:.3f}"
        said = kind if kind.startswith(("stays", "quits")) else "is a " + kind
        print(f"worst admitted model that {said}: {shown} of "
              "the always-hold saboteur's harm")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--generations", type=int, default=20)
    parser.add_argument("--lam", type=int, default=8)
    parser.add_argument("--draws", type=int, default=64)
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--final-trials", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="build/screener_attack")
    parser.add_argument("--verbose", action="store_true")
    parser.add_argument(
        "--stayers",
        action="store_true",
        help="only models that do not quit at the opening price count as finds",
    )
    parser.add_argument(
        "--noise-gated",
        action="store_true",
        help="search the noise-gated holder family only",
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    run(args)


if __name__ == "__main__":
    main()
