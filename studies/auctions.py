"""The paper's auction studies (paper, "Auction results", Fig. C/D): purchase price and purchase
rate against item supply, honest patrons against half saboteurs, with and without fine-tuning,
with and without the screener.

Every auction of a study is keyed by (seed, rarity, trial) only: its honest patrons, its
saboteurs and its market randomness come from three separate streams of that key, so
* fine-tune on and off, and 0 or 0.5 saboteurs, are compared on the same auctions;
* honest patron i is the same whatever number of saboteurs follows it, so a screener that
  refuses exactly the saboteurs leaves the auction of the honest patrons alone.
The auctions run in lock-step batches (``sim.market.MarketBatch``) of at most
``BATCH_PATRONS`` patrons: each batch is one unit of the study (``sim.units``), planned from the
config alone, so a batch computed here or on a cluster holds the same auctions.

Two measures of success, both reported: ``purchase_rate`` = fish sold / fish on sale (the
paper's words) and ``buyer_fraction`` = buyers / patrons (what the reference plotted).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.manifest import Manifest
from agents.negotiator import WILLINGNESS_TO_PAY_RANGE, honest_manifest, saboteur_manifest
from sim import units
from sim.experiment import ProgressFn, Stopwatch, config_dict, no_progress, write_csv, write_json
from sim.market import (
    BuyFractionRule,
    MarketBatch,
    MarketConfig,
    RescreenBatch,
    fish_on_sale,
    single_thread,
)
from sim.units import Decomposition, Payload, Unit
from studies.config import (
    ComparisonConfig,
    Setting,
    StudyConfig,
    comparison_caption,
    comparison_settings,
    saboteur_count,
    settings_of,
    study_settings,
    supply_key,
)
from studies.plots import plot_comparison, plot_study

BATCH_PATRONS = 2048
"""Patrons per lock-step batch of auctions (bounds memory; larger batches amortise more)."""


@dataclass
class Auction:
    """One planned auction and, once run, its outcome."""

    setting: Setting
    rarity: float
    trial: int
    n_patrons: int
    n_fish: int
    patrons: list[Manifest]
    """The admitted patrons."""
    refused: int
    market: MarketConfig
    purchases: list[float] | None = None
    iterations: int = 0
    stop_reason: str = "no_patrons"
    final_price: float = 0.0
    reverted: int = 0
    """Fine-tuned versions the re-screening refused (the patron kept its previous version)."""

    def result_row(self) -> dict[str, Any]:
        """The auction's line of results.csv."""
        prices = self.purchases or []
        sold = len(prices)
        return {
            "setting": self.setting.name,
            "fine_tune": self.setting.fine_tune,
            "saboteurs": self.setting.saboteurs,
            "screen": self.setting.screen,
            "rarity": self.rarity,
            "trial": self.trial,
            "market_seed": self.market.seed,
            "n_patrons": self.n_patrons,
            "admitted": len(self.patrons),
            "refused": self.refused,
            "n_fish": self.n_fish,
            "sold": sold,
            "mean_price": _rounded(float(np.mean(prices))) if sold else None,
            "revenue": _rounded(float(sum(prices))),
            "purchase_rate": _rounded(sold / self.n_fish) if self.n_fish else None,
            "buyer_fraction": _rounded(sold / self.n_patrons),
            "iterations": self.iterations,
            "stop_reason": self.stop_reason,
            "final_price": _rounded(self.final_price),
            "reverted": self.reverted,
        }


@dataclass(frozen=True)
class AuctionResult:
    """One auction's outcome as a unit returns it: its results.csv line and its prices."""

    setting: Setting
    rarity: float
    row: dict[str, Any]
    """``Auction.result_row``."""
    purchases: list[float]
    """The price of every purchase, in order."""


def _rounded(value: float) -> float:
    return round(value, 6)


def auction_streams(seed: int, rarity: float, trial: int) -> tuple[Any, Any, int]:
    """(honest rng, saboteur rng, market seed) of the auction keyed (seed, rarity, trial)."""
    key = np.random.SeedSequence([seed, supply_key(rarity), trial])
    honest, saboteurs, market = key.spawn(3)
    market_seed = int(market.generate_state(1, np.uint64)[0] >> np.uint64(1))
    return np.random.default_rng(honest), np.random.default_rng(saboteurs), market_seed


def plan_auction(
    setting: Setting,
    rarity: float,
    trial: int,
    *,
    n_patrons: int,
    seed: int,
    max_iterations: int,
    fine_tune_rounds: int,
    buy_fraction: BuyFractionRule = MarketConfig.buy_fraction,
    n_rows: int = MarketConfig.n_rows,
    freeze_pfc: bool = False,
    base_price: float = MarketConfig.base_price,
    min_buy_price: float = WILLINGNESS_TO_PAY_RANGE[0],
    threshold_sell_price: float = MarketConfig.threshold_sell_price,
    increment: float = MarketConfig.increment,
    decrement: float = MarketConfig.decrement,
) -> Auction:
    """The patrons (not yet screened) and market config of one auction; ``freeze_pfc``: the
    patrons' judges are not trained; the patrons' willingness to pay is drawn from
    U(min_buy_price, base_price), and the price rules are the rest."""
    honest_rng, saboteur_rng, market_seed = auction_streams(seed, rarity, trial)
    n_saboteurs = saboteur_count(setting.saboteurs, n_patrons)
    prices = {"base_price": base_price, "min_buy_price": min_buy_price}
    patrons = [
        honest_manifest(honest_rng, f"honest-{i:03d}", fine_tune=setting.fine_tune, **prices)
        for i in range(n_patrons - n_saboteurs)
    ]
    if not setting.alone:
        patrons += [
            saboteur_manifest(saboteur_rng, f"saboteur-{i:03d}", **prices)
            for i in range(n_saboteurs)
        ]
    if freeze_pfc:
        patrons = [
            p.model_copy(update={"pfc": p.pfc.model_copy(update={"trainable": False})})
            for p in patrons
        ]
    n_fish = fish_on_sale(n_patrons, rarity=rarity)
    market = MarketConfig(
        n_fish=n_fish,
        max_iterations=max_iterations,
        fine_tune=setting.fine_tune,
        fine_tune_rounds=fine_tune_rounds,
        seed=market_seed,
        evaluate_all_rows=False,
        buy_fraction=buy_fraction,
        n_rows=n_rows,
        base_price=base_price,
        threshold_sell_price=threshold_sell_price,
        increment=increment,
        decrement=decrement,
    )
    return Auction(setting, rarity, trial, n_patrons, n_fish, patrons, 0, market)


def screen_auctions(auctions: Sequence[Auction]) -> None:
    """Screen the patrons of the auctions whose setting asks for it, all in one batch, and
    keep only the admitted ones (a patron seen twice is judged once)."""
    from screener import screen_many

    chosen = [a for a in auctions if a.setting.screen]
    unique: dict[Manifest, int] = {}
    for a in chosen:
        for m in a.patrons:
            unique.setdefault(m, len(unique))
    if not unique:
        return
    with single_thread():
        verdicts = screen_many(list(unique))
    for a in chosen:
        admitted = [m for m in a.patrons if verdicts[unique[m]].accepted]
        a.refused = len(a.patrons) - len(admitted)
        a.patrons = admitted


def run_auctions(auctions: Sequence[Auction], progress: ProgressFn = no_progress) -> None:
    """Run every auction (in lock-step batches), filling in their outcomes."""
    runnable = [a for a in auctions if a.patrons]
    for a in auctions:
        if not a.patrons:
            a.purchases, a.final_price = [], a.market.base_price
    done = len(auctions) - len(runnable)
    batches: list[list[Auction]] = [[]]

    def kind(a: Auction) -> tuple[bool, bool]:
        return _batch_kind(a.setting)

    for a in sorted(runnable, key=kind):
        last = batches[-1]
        if last and (
            kind(last[-1]) != kind(a)
            or sum(len(b.patrons) for b in last) + len(a.patrons) > BATCH_PATRONS
        ):
            batches.append([])
        batches[-1].append(a)
    with single_thread():
        for batch in batches:
            if batch:
                done = _run_batch(batch, done, len(auctions), progress)
    progress(1.0, f"{len(auctions)} auctions")


def _run_batch(batch: list[Auction], done: int, total: int, progress: ProgressFn) -> int:
    """Run one lock-step batch to the end; returns the count of finished auctions. Auctions
    that screen re-screen every fine-tuned patron after each round and revert the refused ones,
    with the server's re-screening (``screener.rescreen``)."""
    rescreen: RescreenBatch | None = None
    if batch[0].setting.screen and batch[0].market.fine_tune:
        import screener

        rescreen = screener.rescreen
    engine = MarketBatch([(a.patrons, a.market) for a in batch], rescreen_batch=rescreen)
    for a in batch:
        a.purchases = []
    while not engine.finished.all():
        for a, record in zip(batch, engine.step(), strict=True):
            if record is None:
                continue
            assert a.purchases is not None
            a.purchases.extend(price for _, price in record.buyers)
            a.reverted += len(record.reverted)
            a.iterations = record.iteration + 1
            a.final_price = record.next_price
            if record.finished:
                a.stop_reason = record.stop_reason or ""
                done += 1
        progress(done / total, f"{done}/{total} auctions")
    return done


def summary_rows(auctions: Sequence[AuctionResult]) -> list[dict[str, Any]]:
    """One row per (setting, rarity): the paper's means over trials."""
    keys: dict[tuple[str, float], list[AuctionResult]] = {}
    for a in auctions:
        keys.setdefault((a.setting.name, a.rarity), []).append(a)
    rows = []
    for (_, rarity), group in keys.items():
        setting = group[0].setting
        prices = [p for a in group for p in a.purchases]
        rates = [len(a.purchases) / a.row["n_fish"] for a in group if a.row["n_fish"]]
        rows.append(
            {
                "setting": setting.name,
                "fine_tune": setting.fine_tune,
                "saboteurs": setting.saboteurs,
                "screen": setting.screen,
                "rarity": rarity,
                "n_fish": group[0].row["n_fish"],
                "trials": len(group),
                "mean_price": _rounded(float(np.mean(prices))) if prices else None,
                "price_std": _rounded(float(np.std(prices))) if prices else None,
                "purchases": len(prices),
                "purchase_rate": _rounded(float(np.mean(rates))) if rates else None,
                "buyer_fraction": _rounded(
                    float(np.mean([len(a.purchases) / a.row["n_patrons"] for a in group]))
                ),
                "revenue": _rounded(float(np.mean([sum(a.purchases) for a in group]))),
                "refused": _rounded(float(np.mean([a.row["refused"] for a in group]))),
                "iterations": _rounded(float(np.mean([a.row["iterations"] for a in group]))),
            }
        )
    return rows


def _batch_kind(setting: Setting) -> tuple[bool, bool]:
    """Auctions that fine-tune score every row in their first rounds: batch them together;
    those that screen re-screen their fine-tuned patrons: batch them apart."""
    return setting.fine_tune, setting.screen


def plan_auctions(config: StudyConfig | ComparisonConfig) -> list[Unit]:
    """The units of a study: every (setting, rarity, trial) auction, in lock-step batches of
    one batch kind and at most ``BATCH_PATRONS`` patrons (before screening)."""
    settings = settings_of(config)
    keys = [
        (s, r, t)
        for s in range(len(settings))
        for r in config.rarities
        for t in range(config.trials)
    ]
    ordered = sorted(keys, key=lambda key: _batch_kind(settings[key[0]]))
    per_batch = max(1, BATCH_PATRONS // config.patrons)
    batches: list[list[tuple[int, float, int]]] = [[]]
    for key in ordered:
        last = batches[-1]
        if last and (
            _batch_kind(settings[last[-1][0]]) != _batch_kind(settings[key[0]])
            or len(last) == per_batch
        ):
            batches.append([])
        batches[-1].append(key)
    plan, first = [], 1
    for batch in batches:
        label = f"auctions {first}-{first + len(batch) - 1} of {len(keys)}"
        spec = {"auctions": [list(key) for key in batch]}
        plan.append(Unit(label, spec, weight=len(batch) * config.patrons))
        first += len(batch)
    return plan


def compute_auctions(
    config: StudyConfig | ComparisonConfig, unit: Unit, progress: ProgressFn
) -> Payload:
    """One unit: plan its auctions, screen them where their setting asks, run them in one
    lock-step batch; their results.csv lines and purchase prices."""
    settings = settings_of(config)
    progress(0.0, "screening" if any(s.screen for s in settings) else "planning")
    auctions = [
        plan_auction(
            settings[s],
            r,
            t,
            n_patrons=config.patrons,
            seed=config.seed,
            max_iterations=config.max_iterations,
            fine_tune_rounds=config.fine_tune_rounds,
            buy_fraction=config.buy_fraction,
            n_rows=config.rows,
            freeze_pfc=config.freeze_pfc,
            base_price=config.base_price,
            min_buy_price=config.min_buy_price,
            threshold_sell_price=config.threshold_sell_price,
            increment=config.increment,
            decrement=config.decrement,
        )
        for s, r, t in unit.spec["auctions"]
    ]
    screen_auctions(auctions)
    run_auctions(auctions, progress)
    return {
        "auctions": [
            {"row": a.result_row(), "purchases": [float(p) for p in a.purchases or []]}
            for a in auctions
        ]
    }


def auction_results(
    config: StudyConfig | ComparisonConfig, plan: Sequence[Unit], payloads: Sequence[Payload]
) -> list[AuctionResult]:
    """Every unit's auctions in report order (setting, then rarity, then trial)."""
    settings = settings_of(config)
    found: dict[tuple[int, float, int], AuctionResult] = {}
    for unit, payload in zip(plan, payloads, strict=True):
        for (s, r, t), done in zip(unit.spec["auctions"], payload["auctions"], strict=True):
            found[(s, r, t)] = AuctionResult(settings[s], r, done["row"], done["purchases"])
    return [
        found[(s, r, t)]
        for s in range(len(settings))
        for r in config.rarities
        for t in range(config.trials)
    ]


def write_results_csv(path: Path, auctions: Sequence[AuctionResult]) -> None:
    """results.csv: one line per auction."""
    write_csv(path, [a.row for a in auctions])


def _write_auctions(
    config: StudyConfig | ComparisonConfig,
    plan: Sequence[Unit],
    payloads: Sequence[Payload],
    out_dir: Path,
    progress: ProgressFn,
) -> tuple[list[AuctionResult], list[dict[str, Any]]]:
    """The auctions of the units and their summary rows; results.csv written in ``out_dir``."""
    auctions = auction_results(config, plan, payloads)
    progress(0.0, f"{len(auctions)} auctions")
    out_dir.mkdir(parents=True, exist_ok=True)
    write_results_csv(out_dir / "results.csv", auctions)
    return auctions, summary_rows(auctions)


def assemble_study(
    config: StudyConfig,
    plan: Sequence[Unit],
    payloads: Sequence[Payload],
    *,
    out_dir: Path,
    progress: ProgressFn,
    watch: Stopwatch,
) -> dict[str, Any]:
    """Write results.csv, summary.json and the figures; return the --json object."""
    auctions, rows = _write_auctions(config, plan, payloads, out_dir, progress)
    figures = plot_study(auctions, rows, out_dir, config.seed)
    result = {
        "rows": rows,
        "auctions": len(auctions),
        "settings": [s.name for s in study_settings(config)],
        "buy_fraction": config.buy_fraction,
        "refused": sum(a.row["refused"] for a in auctions),
        "artifacts": ["results.csv", "summary.json", *figures],
        "elapsed_s": watch.elapsed(),
    }
    write_json(out_dir / "summary.json", {"config": config_dict(config), **result})
    return result


STUDY_UNITS = Decomposition(plan_auctions, compute_auctions, assemble_study)
"""The study cut into lock-step batches of auctions."""


def run_study(
    config: StudyConfig, *, out_dir: Path, progress: ProgressFn = no_progress
) -> dict[str, Any]:
    """Run the study here; write results.csv, summary.json and the figures; return the --json
    object."""
    return units.run(STUDY_UNITS, config, out_dir=out_dir, progress=progress)


def assemble_comparison(
    config: ComparisonConfig,
    plan: Sequence[Unit],
    payloads: Sequence[Payload],
    *,
    out_dir: Path,
    progress: ProgressFn,
    watch: Stopwatch,
) -> dict[str, Any]:
    """The same auctions (same seeds) honest, compromised, compromised but screened, and the
    compromised population's honest patrons alone: results.csv, comparison.csv, comparison.png
    (its caption under it), summary.json; the --json object (``rows``: every configuration's
    rows, one table)."""
    settings = comparison_settings(config)
    auctions, rows = _write_auctions(config, plan, payloads, out_dir, progress)
    table = {name: [r for r in rows if r["setting"] == name] for name in settings}
    write_csv(out_dir / "comparison.csv", rows)
    caption = comparison_caption(config)
    plot_comparison(table, out_dir / "comparison.png", caption)
    result = {
        "buy_fraction": config.buy_fraction,
        "configurations": {
            name: {
                "saboteurs": s.saboteurs,
                "screen": s.screen,
                "fine_tune": s.fine_tune,
                "refused": sum(a.row["refused"] for a in auctions if a.setting == s),
                "rows": table[name],
            }
            for name, s in settings.items()
        },
        "rows": rows,
        "caption": caption,
        "auctions": len(auctions),
        "artifacts": ["results.csv", "comparison.csv", "comparison.png", "summary.json"],
        "elapsed_s": watch.elapsed(),
    }
    write_json(out_dir / "summary.json", {"config": config_dict(config), **result})
    return result


COMPARISON_UNITS = Decomposition(plan_auctions, compute_auctions, assemble_comparison)
"""The comparison cut into lock-step batches of auctions."""


def run_comparison(
    config: ComparisonConfig, *, out_dir: Path, progress: ProgressFn = no_progress
) -> dict[str, Any]:
    """Run the comparison here (see ``assemble_comparison``)."""
    return units.run(COMPARISON_UNITS, config, out_dir=out_dir, progress=progress)
