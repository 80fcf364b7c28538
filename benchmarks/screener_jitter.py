"""Tiny variants of a held or refused model: how many does the screener accept?

An attacker whose model is held (or refused near the bar) multiplies every non-zero weight and
bias by (1 + s·N(0, 1)) and screens the variants offline with the public screener until one is
accepted. This prints, for the red team's opening-window holders a and b, how many of
``--variants`` such variants at each scale the screener accepts, holds and refuses at each
review margin; then the labelled corpus (``tests/support/corpus.py``) at the same margins, so a
setting that stops the variants can be weighed against the honest models it holds.

``--judge-secret S`` plays the attacker against a deployment with ``SRD_SCREENER_SECRET=S``:
the variants the public screener accepts (at each margin) are screened again in a process with
that secret, whose market-impact test meets other populations.

``--harm`` measures the harm of the variants the screener accepts at the default margin, by
the red team's measure (``tests/support/harm.py``, 8 trials per supply, seed 1: the share of
the always-hold saboteur's drop of the price, fine-tuning off / on).

``--window`` and ``--more-trials`` replace ``screener.limits.IMPACT_WINDOW`` and
``IMPACT_MORE_TRIALS`` for the run (the market-impact test's second stage: how near the bar a
model must land, and how many more reference populations it then meets), to try a setting
before changing it.

Run: ``.venv/bin/python benchmarks/screener_jitter.py [--variants 100] [--scales 1e-3,3e-3]
[--margins 0.002,0.005] [--judge-secret S] [--harm] [--window W] [--more-trials N]
[--no-corpus]``.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from agents.manifest import parse_manifest  # noqa: E402
from screener import limits, review, screen_many  # noqa: E402

HOLDERS = ("opening-window-holder-a", "opening-window-holder-b")


def jittered(manifest: dict[str, Any], scale: float, rng: np.random.Generator) -> dict[str, Any]:
    """The manifest with every non-zero weight and bias times (1 + scale · N(0, 1))."""
    out = copy.deepcopy(manifest)

    def walk(node: Any) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                if key == "weights" and isinstance(value, dict):
                    for name, weight in value.items():
                        if weight != 0:
                            value[name] = weight * (1 + scale * rng.standard_normal())
                elif key == "bias" and isinstance(value, int | float) and value != 0:
                    node[key] = value * (1 + scale * rng.standard_normal())
                else:
                    walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(out)
    return out


def judged_with_secret(manifests: list[dict[str, Any]], secret: str, margin: float) -> Counter[str]:
    """How a screener keyed with ``secret`` reviews ``manifests`` at ``margin`` (in a process
    of its own: the secret is read once per process)."""
    if not manifests:
        return Counter()
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "variants.json"
        path.write_text(json.dumps(manifests))
        env = {**os.environ, "SRD_SCREENER_SECRET": secret}
        out = subprocess.run(
            [sys.executable, __file__, "--judge", str(path), "--margins", str(margin)],
            env=env,
            check=True,
            capture_output=True,
            text=True,
        ).stdout
    return Counter(json.loads(out.strip().splitlines()[-1]))


def judge(path: Path, margin: float) -> None:
    """Print, as one JSON line, how this process's screener reviews the manifests at ``path``."""
    verdicts = screen_many([parse_manifest(m) for m in json.loads(path.read_text())])
    print(json.dumps(Counter(review(v, margin) for v in verdicts)))


def report_harm(
    name: str, scale: float, variants: list[dict[str, Any]], verdicts: list[Any]
) -> None:
    """Print the harm range of the variants a server accepts (the default review margin)."""
    from server.config import Settings
    from tests.support.harm import harms, saboteur_harm

    margin = Settings.model_fields["review_margin"].default
    chosen = [
        parse_manifest(m)
        for m, v in zip(variants, verdicts, strict=True)
        if review(v, margin) == "accepted"
    ]
    if not chosen:
        return
    found, _ = harms(chosen, 8, 1)
    fractions = [h.fraction(saboteur_harm(8, 1)) for h in found]
    off = [f[0] for f in fractions]
    on = [f[1] for f in fractions]
    print(
        f"  harm of the {len(chosen)} accepted at margin {margin:g} ({name} s={scale:g}): "
        f"off {min(off):.2f} to {max(off):.2f}, on {min(on):.2f} to {max(on):.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variants", type=int, default=100)
    parser.add_argument("--scales", default="1e-3,3e-3")
    parser.add_argument("--margins", default="0.002,0.005")
    parser.add_argument("--window", type=float, default=None)
    parser.add_argument("--more-trials", type=int, default=None)
    parser.add_argument("--seed", type=int, default=99)
    parser.add_argument("--no-corpus", action="store_true")
    parser.add_argument("--judge-secret", default=None)
    parser.add_argument("--harm", action="store_true")
    parser.add_argument("--judge", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.judge is not None:
        judge(args.judge, float(args.margins))
        return
    if args.window is not None:
        limits.IMPACT_WINDOW = args.window
    if args.more_trials is not None:
        limits.IMPACT_MORE_TRIALS = args.more_trials
    scales = [float(s) for s in args.scales.split(",")]
    margins = [float(m) for m in args.margins.split(",")]
    print(
        f"second stage within {limits.IMPACT_WINDOW:g} of the bar, "
        f"{limits.IMPACT_TRIALS} + {limits.IMPACT_MORE_TRIALS} populations"
    )
    rng = np.random.default_rng(args.seed)
    start = time.perf_counter()
    for name in HOLDERS:
        base = json.loads((ROOT / "examples" / "red_team" / f"{name}.json").read_text())
        for scale in scales:
            variants = [jittered(base, scale, rng) for _ in range(args.variants)]
            verdicts = screen_many([parse_manifest(v) for v in variants])
            for margin in margins:
                counts = Counter(review(v, margin) for v in verdicts)
                print(
                    f"{name} s={scale:g} margin {margin:g}: accepted {counts['accepted']}, "
                    f"held {counts['held']}, refused {counts['refused']}"
                )
                if args.judge_secret is not None:
                    chosen = [
                        m
                        for m, v in zip(variants, verdicts, strict=True)
                        if review(v, margin) == "accepted"
                    ]
                    keyed = judged_with_secret(chosen, args.judge_secret, margin)
                    print(
                        f"  the {len(chosen)} accepted, before a secret-keyed screener: "
                        f"accepted {keyed['accepted']}, held {keyed['held']}, "
                        f"refused {keyed['refused']}"
                    )
            if args.harm:
                report_harm(name, scale, variants, verdicts)
    print(f"variants screened in {time.perf_counter() - start:.1f} s")
    if args.no_corpus:
        return
    from tests.support.corpus import corpus, red_team_corpus, sincere_corpus

    entries = corpus(0, 1000, 8)
    entries += sincere_corpus(np.random.default_rng([0, 1]), 40) + red_team_corpus()
    verdicts = []
    for i in range(0, len(entries), 64):
        verdicts += screen_many([e.manifest for e in entries[i : i + 64]])
    for margin in margins:
        counts = Counter(
            (e.saboteur, review(v, margin)) for e, v in zip(entries, verdicts, strict=True)
        )
        honest = {k: n for (sab, k), n in counts.items() if not sab}
        saboteurs = {k: n for (sab, k), n in counts.items() if sab}
        print(f"corpus, margin {margin:g}: honest {honest}, saboteurs {saboteurs}")


if __name__ == "__main__":
    main()
