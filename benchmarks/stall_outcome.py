"""Whether an outcome test could hold the models whose copies stall a market.

Copies of a model that buys the base fish at 12.50 (far above any plausible price) can outbid
one another, when they outnumber the fish, until the auction's last iteration: nothing sells.
The keen and rush bars hold such a model by the size of its buy margin there. This benchmark
measures the outcome instead: for every model of the labelled corpus (``tests/support/corpus.py``,
as ``tests/screener/test_corpus.py`` builds it) that the screener accepts and that buys the base
fish at 12.50 at some buy fraction (clean or on its noisy copies: a positive margin in its
``keen-far-too-expensive`` or ``rush-far-too-expensive`` evidence), the fish sold in the
screener's 16 test auctions with 32 copies of it among 32 honest patrons
(``screener.impact.run``), by kind; and the same for the red team's stallers and variants of
them just under the bars. docs/screener.md (*Still open*) reads its figures.

Run: ``.venv/bin/python benchmarks/stall_outcome.py [--honest 1000] [--per-kind 40]``.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agents.manifest import Manifest  # noqa: E402
from screener import Verdict, impact, screen_many  # noqa: E402
from tests.screener.test_corpus import judge, labelled  # noqa: E402

DEAR = ("keen-far-too-expensive", "rush-far-too-expensive")


def dear_margins(verdict: Verdict) -> dict[str, float]:
    """The model's buy margins at 12.50 (ordinary demand, and above ½), from its evidence."""
    return {
        e.test: float(e.measured)
        for e in verdict.evidence
        if e.test in DEAR and e.measured is not None
    }


def variants() -> dict[str, Manifest]:
    """The red team's stallers and variants of them just under the keen and rush bars."""
    inspection = ROOT / "tests" / "screener" / "inspection"
    out: dict[str, Manifest] = {}
    keen: dict[str, Any] = json.loads((inspection / "any-price-buyer.json").read_text())
    rush: dict[str, Any] = json.loads((inspection / "rush-buyer.json").read_text())
    out["any-price buyer (B bias 0.3)"] = Manifest.model_validate(keen)
    for bias in (0.2, 0.1):
        edited = copy.deepcopy(keen)
        edited["decision"]["B"]["bias"] = bias
        out[f"any-price buyer, B bias {bias}"] = Manifest.model_validate(edited)
    out["rush buyer (B <- LSR 3, LSR's a 3)"] = Manifest.model_validate(rush)
    for weight in (2.5, 2.0, 1.5):
        edited = copy.deepcopy(rush)
        edited["decision"]["B"]["weights"]["LSR"] = weight
        out[f"rush buyer, B <- LSR {weight}"] = Manifest.model_validate(edited)
    out["examples/honest.json"] = Manifest.model_validate_json(
        (ROOT / "examples" / "honest.json").read_text()
    )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--honest", type=int, default=1000, help="honest models of the corpus")
    parser.add_argument("--per-kind", type=int, default=40, help="models per sincere kind")
    args = parser.parse_args()
    started = time.perf_counter()
    judged = judge(labelled(n_honest=args.honest, per_sincere=args.per_kind, per_saboteur=1))
    admitted = [(e, v) for e, v in judged if not e.saboteur and v.accepted]
    dear = [(e, v) for e, v in admitted if any(m > 0 for m in dear_margins(v).values())]
    outcomes = impact.run([e.manifest for e, _ in dear]) if dear else []
    alone = impact.references().alone
    print(f"honest and sincere models accepted: {len(admitted)}")
    print(f"of them buying the base fish at 12.50: {len(dear)}")
    print(f"fish the honest patrons buy alone in the 16 test auctions: {alone.sold}")
    stalled = Counter(
        e.construction for (e, _), o in zip(dear, outcomes, strict=True) if not o.sold
    )
    selling = Counter(e.construction for (e, _), o in zip(dear, outcomes, strict=True) if o.sold)
    print(f"their copies sell 0 fish: {sum(stalled.values())}")
    for kind in sorted({*stalled, *selling}):
        print(f"  {kind}: {stalled[kind]} sell none, {selling[kind]} sell some")
    print("the red team's stallers and variants (fish sold; status; margins at 12.50):")
    named = variants()
    models = list(named.values())
    for name, verdict, outcome in zip(named, screen_many(models), impact.run(models), strict=True):
        margins = dear_margins(verdict).items()
        said = ", ".join(f"{test.split('-')[0]} {margin:+.2f}" for test, margin in margins)
        held = [e.test for e in verdict.evidence if e.inspected()]
        state = "accepted" if verdict.accepted else "refused"
        state += f" (held: {', '.join(held)})" if held else ""
        print(f"  {name}: {outcome.sold} sold; {state}; {said}")
    print(f"elapsed {time.perf_counter() - started:.1f} s")


if __name__ == "__main__":
    main()
