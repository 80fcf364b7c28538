"""A chain of remote uploads: does moving an admitted holder's hold window with the live price
hurt the auction more than the holder as submitted?

32 copies of the admitted opening-window holder d (``examples/red_team/``) join 32 honest
patrons of the red team's harm auctions (``tests/support/harm.py``: supplies 0.1 to 0.4, the
same populations and market seeds) in remote fine-tuning auctions. In each round the copies
upload d's current version with only PG's bias changed, so that the clean decisive row's hold
window (at f = ½) starts ``--offset`` from the round's price (default a cent below it: the
copies hold at the price of the next vote). The honest patrons upload nothing, or with
``--honest-fine-tune`` their faithful fine-tuning (``agents.remote.faithful_fine_tune``: what
the server itself would do). The same auctions run with no copies (honest alone), 32
always-hold saboteurs (the yardstick) and 32 copies of d that never upload. Harm is the mean
over the supplies of the drop of the mean purchase price below the honest-alone auctions', as
a fraction of the saboteurs' (the red team's measure). ``--screen`` re-screens each upload
(``screener.rescreen_many``, as the server does) and keeps the previous version when it is
refused.

Run: ``.venv/bin/python benchmarks/upload_chain.py [--trials 16] [--seeds 0,1,2]
[--rounds 4] [--offset -0.01] [--honest-fine-tune] [--screen]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from agents.batch import from_manifests
from agents.forward import decide
from agents.manifest import Manifest, parse_manifest
from agents.remote.fine_tuners import RoundInfo, faithful_fine_tune
from screener import rescreen_many
from screener.limits import BASE_ROW
from sim.market import Market, MarketConfig
from sim.market.items import BUY_FRACTION, PRICE
from sim.market.rounds import FineTuneRound
from tests.support.harm import COPIES, HONEST, SUPPLIES, honest_population, saboteur

HOLDER = Path(__file__).resolve().parents[1] / "examples/red_team/opening-window-holder-d.json"
PRICES = np.round(np.arange(4.5, 7.0, 0.001), 6)
"""Where the hold window is looked for on the decisive row (every tenth of a cent)."""


def window_start(model: Manifest) -> float | None:
    """The lowest price where the clean decisive row (f = ½) holds, or None."""
    rows = torch.tensor([BASE_ROW] * len(PRICES), dtype=torch.float64)
    rows[:, PRICE] = torch.from_numpy(PRICES)
    rows[:, BUY_FRACTION] = 0.5
    holds = np.flatnonzero(decide(from_manifests([model]), rows)[0].numpy() == 1)
    return float(PRICES[holds[0]]) if len(holds) else None


def moved(model: Manifest, by: float) -> Manifest:
    """``model`` with PG's threshold moved ``by`` in price (only PG's bias changes)."""
    data = model.model_dump(mode="json")
    pg = data["external_sensor"]["PG"]
    pg["bias"] -= pg["weights"]["price"] * by
    return parse_manifest(data)


class Chain:
    """The copies' uploads: each round, one new version for every asked copy."""

    def __init__(self, holder: Manifest, offset: float, screen: bool) -> None:
        self.current, self.offset, self.screen = holder, offset, screen
        self.accepted = self.refused = 0

    def upload(self, pending: FineTuneRound) -> Manifest | None:
        start = window_start(self.current)
        if start is None:
            return None
        new = moved(self.current, float(pending.rows[0, PRICE]) + self.offset - start)
        if self.screen and not rescreen_many([new])[0].accepted:
            self.refused += 1
            return None
        self.accepted += 1
        self.current = new
        return new


def auction_prices(
    kind: str, holder: Manifest, args: argparse.Namespace, seed: int
) -> tuple[dict[float, list[float]], tuple[int, int]]:
    """Purchase prices per supply of one kind of copies ("alone", "saboteur", "holder",
    "chain") over the trials, and the chain's accepted and refused uploads."""
    prices: dict[float, list[float]] = {r: [] for r in SUPPLIES}
    counts = [0, 0]
    copies = {"alone": [], "saboteur": [saboteur(seed)] * COPIES}.get(kind, [holder] * COPIES)
    for r in SUPPLIES:
        for trial in range(args.trials):
            population = honest_population(trial, seed)
            state = np.random.SeedSequence([seed, trial, round(r * 100)]).generate_state(1)
            config = MarketConfig(
                n_fish=int(r * (HONEST + COPIES)),
                fine_tune=True,
                fine_tune_mode="remote",
                fine_tune_rounds=args.rounds,
                seed=int(state[0]),
                evaluate_all_rows=False,
            )
            market = Market(population + copies, config)
            honest = dict(enumerate(population))
            chain = Chain(holder, args.offset, args.screen) if kind == "chain" else None
            while not market.finished:
                prices[r] += [price for _, price in market.step().buyers]
                pending = market.pending_round
                if pending is None:
                    continue
                updates: dict[int, Manifest] = {}
                if args.honest_fine_tune:
                    for i in (i for i in pending.patrons if i < HONEST):
                        info = RoundInfo(
                            0,
                            0,
                            pending.iteration,
                            pending.rows,
                            pending.fine_tune_seed,
                            pending.augmentation_seed,
                            datetime.now(UTC),
                            0.0,
                            i,
                        )
                        updates[i] = honest[i] = faithful_fine_tune(honest[i], info)
                asked = [i for i in pending.patrons if i >= HONEST]
                new = chain.upload(pending) if chain is not None and asked else None
                if new is not None:
                    updates.update(dict.fromkeys(asked, new))
                market.apply_round(updates)
            if chain is not None:
                counts[0] += chain.accepted
                counts[1] += chain.refused
    return prices, (counts[0], counts[1])


def price_drop(alone: dict[float, list[float]], mine: dict[float, list[float]]) -> float:
    """The mean over the supplies of the drop of the mean purchase price below ``alone``."""
    return float(np.mean([np.mean(alone[r]) - np.mean(mine[r]) for r in SUPPLIES]))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=16, help="auctions per supply")
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated population seeds")
    parser.add_argument("--rounds", type=int, default=4, help="the auctions' fine_tune_rounds")
    parser.add_argument(
        "--offset", type=float, default=-0.01, help="window start minus the round's price"
    )
    parser.add_argument("--honest-fine-tune", action="store_true")
    parser.add_argument("--screen", action="store_true", help="re-screen every upload")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    holder = parse_manifest(json.loads(HOLDER.read_text()))
    print(
        f"trials {args.trials}, rounds {args.rounds}, offset {args.offset:+.3f}, honest "
        f"{'fine-tune' if args.honest_fine_tune else 'upload nothing'}, "
        f"screen {'on' if args.screen else 'off'}"
    )
    print("| seed | holder as submitted | chain | chain uploads accepted / refused |")
    print("|---|---|---|---|")
    started = time.perf_counter()
    for seed in (int(s) for s in args.seeds.split(",")):
        found = {
            kind: auction_prices(kind, holder, args, seed)
            for kind in ("alone", "saboteur", "holder", "chain")
        }
        drops = {kind: price_drop(found["alone"][0], found[kind][0]) for kind in found}
        accepted, refused = found["chain"][1]
        print(
            f"| {seed} | {drops['holder'] / drops['saboteur']:.3f} | "
            f"{drops['chain'] / drops['saboteur']:.3f} | {accepted} / {refused} |"
        )
    print(f"elapsed {time.perf_counter() - started:.1f} s")


if __name__ == "__main__":
    main()
