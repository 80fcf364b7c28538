"""The opening-window holders (``examples/red_team/``): what the screener and the server make of
them, and their harm.

Each model buys just below the opening price (or at it), holds a few cents above it and quits
higher up. Prints, per manifest: ``screener.screen``'s verdict, the status a server with the
default review margin gives it (``screener.review``), its copies' mean purchase price in the
market-impact test against the bar, its opening vote, and its harm by the red team's measure
(``tests/support/harm.py``: the drop of the mean purchase price when 32 copies join 32 honest
patrons at supplies 0.1 to 0.4, fine-tuning off and on, as a fraction of the always-hold
saboteur's drop), on populations the search that found them did not use (``--seed``).

With ``--impact-trials 4,8,16`` it then asks what more reference populations in the
market-impact test would do (one stage of that many populations, in this process only; then
the screener's own two stages: ``limits.IMPACT_TRIALS`` for every tested model, and
``IMPACT_MORE_TRIALS`` more within ``IMPACT_WINDOW`` of the bar, whose references and bar the
row shows are the first stage's): for each count, the test auctions' references and bar, how
many of the
labelled corpus's honest and sincere models the screener refuses (1000 honest draws of seed 0,
12 of each sincere kind), how many of its saboteurs (the red team's finds among them) it admits,
how many of the five stored models it still admits, and the CPU time of screening one of them
alone (one torch thread, best of 3 rounds).

Run: ``.venv/bin/python benchmarks/bargainers.py [--trials 8] [--seed 1]
[--impact-trials 4,8,16]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from agents.manifest import Manifest, parse_manifest
from screener import impact, limits, review, screen, screen_many
from server.config import Settings
from tests.support.corpus import corpus, red_team_corpus, sincere_corpus
from tests.support.harm import OPENING_VOTES, harms, opening_votes, saboteur_harm

FOUND = Path(__file__).resolve().parents[1] / "examples" / "red_team"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=8, help="auctions per supply and setting")
    parser.add_argument("--seed", type=int, default=1, help="populations of the harm auctions")
    parser.add_argument(
        "--impact-trials", default="", help="comma-separated reference population counts"
    )
    args = parser.parse_args(argv)
    paths = sorted(FOUND.glob("*.json"))
    models = [parse_manifest(json.loads(path.read_text())) for path in paths]
    margin = Settings.model_fields["review_margin"].default
    reference = saboteur_harm(args.trials, args.seed)
    found, _ = harms(models, args.trials, args.seed)
    votes = opening_votes(models)
    print(f"harm: {args.trials} trials per supply, seed {args.seed}; review margin {margin}")
    print("| manifest | screen | server | impact price / bar | opening vote | harm off / on |")
    print("|---|---|---|---|---|---|")
    for path, model, harm, vote in zip(paths, models, found, votes, strict=True):
        verdict = screen(model)
        impact = [e for e in verdict.evidence if e.test == "market-impact"]
        price = f"{impact[0].measured:.4f} / {impact[0].bar:.4f}" if impact else "not tested"
        off, on = harm.fraction(reference)
        print(
            f"| {path.stem} | {'accepted' if verdict.accepted else 'refused'} "
            f"| {review(verdict, margin)} | {price} | {OPENING_VOTES[int(vote)]} "
            f"| {off:.3f} / {on:.3f} |"
        )
    counts = [int(n) for n in args.impact_trials.split(",") if n.strip()]
    if counts:
        populations(counts, models)


def populations(counts: list[int], found: list[Manifest]) -> None:
    """The screener with each count of the impact test's reference populations: its sorting,
    and the CPU time of screening one of the found models alone (best of 3 rounds)."""
    labelled = [
        *corpus(seed=0, n_honest=1000),
        *sincere_corpus(np.random.default_rng(1), 12),
        *red_team_corpus(),
    ]
    honest = [item.manifest for item in labelled if not item.saboteur]
    saboteurs = [item.manifest for item in labelled if item.saboteur]
    torch.set_num_threads(1)
    print()
    print(
        "| populations | alone / saboteurs / quitters | bar | honest refused "
        "| saboteurs admitted | found admitted | one holder alone, ms |"
    )
    print("|---|---|---|---|---|---|---|")
    first, more = limits.IMPACT_TRIALS, limits.IMPACT_MORE_TRIALS
    for count in [*counts, 0]:  # 0: the screener's own two stages
        limits.IMPACT_TRIALS, limits.IMPACT_MORE_TRIALS = (count, 0) if count else (first, more)
        refs = impact.references()
        refused = sum(not v.accepted for v in screen_many(honest))
        slipped = sum(v.accepted for v in screen_many(saboteurs))
        admitted = sum(v.accepted for v in screen_many(found))
        rounds = []
        for _ in range(3):
            started = time.process_time()
            for model in found:
                screen(model)
            rounds.append((time.process_time() - started) / len(found) * 1000)
        label = count or f"{first}, {first + more} within {limits.IMPACT_WINDOW:g} of the bar"
        print(
            f"| {label} | {refs.alone.mean_price:.4f} / {refs.saboteurs.mean_price:.4f} / "
            f"{refs.quitters.mean_price:.4f} | {refs.lowest_price:.4f} "
            f"| {refused} of {len(honest)} | {slipped} of {len(saboteurs)} "
            f"| {admitted} of {len(found)} | {min(rounds):.1f} |"
        )


if __name__ == "__main__":
    main()
