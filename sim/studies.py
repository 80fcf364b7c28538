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

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import Field

from agents.manifest import Manifest
from agents.negotiator import honest_manifest, saboteur_manifest
from sim import units
from sim.experiment import Cost, ProgressFn, Stopwatch, config_dict, no_progress, write_json
from sim.market import MarketBatch, MarketConfig, RescreenBatch, fish_on_sale, single_thread
from sim.units import Decomposition, Payload, Unit

PAPER_RARITIES = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
"""The paper's item supplies."""
COMPARISON_RARITIES = (0.1, 0.3, 0.5, 0.7, 0.9)
"""The comparison's default supplies (small enough for the demo)."""
GRID_SABOTEURS = 0.5
"""The saboteur fraction of the grid's and the comparison's compromised auctions."""
BATCH_PATRONS = 2048
"""Patrons per lock-step batch of auctions (bounds memory; larger batches amortise more)."""
JITTER = 0.02
"""Half-width of the x jitter of the purchase dots (the reference's)."""

Rarity = Annotated[float, Field(gt=0, le=1)]
Rarities = Annotated[tuple[Rarity, ...], Field(min_length=1, max_length=100)]
AUCTION_COST_S = 0.01
"""Compute of one auction of 64 patrons without fine-tuning, for the job budget: about twice
the lock-step engine's measured cost per auction."""
FINE_TUNED_AUCTION_COST_S = 0.05
"""The same with fine-tuning (measured about 0.02 s per auction)."""
SCREENING_COST_S = 0.01
"""Screening one patron (the behavioural tests included), with a margin."""


@dataclass(frozen=True)
class AuctionOptions:
    """What every auction of a study shares (the study configs add their grid)."""

    patrons: Annotated[int, Field(ge=1, le=1024)] = 64
    """Patrons per auction, saboteurs included."""
    fine_tune: bool = False
    """Patrons fine-tune themselves (SRD) in the first rounds."""
    max_iterations: Annotated[int, Field(ge=1, le=1000)] = MarketConfig.max_iterations
    """Iterations per auction at most."""
    fine_tune_rounds: Annotated[int, Field(ge=0, le=1000)] = MarketConfig.fine_tune_rounds
    """Fine-tuning after each of the first this-many iterations (reference: 5)."""
    seed: Annotated[int, Field(ge=0, le=2**31 - 1)] = 0
    """Seed of every auction: each is keyed by (seed, rarity, trial)."""

    def _auction_cost(self, setting: Setting) -> float:
        """Estimated compute of one auction of ``setting``."""
        per_auction = FINE_TUNED_AUCTION_COST_S if setting.fine_tune else AUCTION_COST_S
        screening = SCREENING_COST_S if setting.screen else 0.0
        return self.patrons * (per_auction / 64 + screening)


@dataclass(frozen=True)
class StudyConfig(AuctionOptions):
    """Fish sale auctions without HTTP: purchase price and rate against item supply.

    The paper's Fig. C/D grid (``srd auction-study``)."""

    rarities: Rarities = PAPER_RARITIES
    """Item supplies r; fish on sale = int(r · patrons)."""
    trials: Annotated[int, Field(ge=1, le=1000)] = 10
    """Independent auctions per supply (and per setting)."""
    saboteurs: Annotated[float, Field(ge=0, le=1)] = 0.0
    """Fraction of the patrons that are always-hold saboteurs (the last ones)."""
    screen: bool = False
    """Screen every patron before the auction (refused ones stay out) and re-screen fine-tuned
    patrons after each round (refused versions are reverted)."""
    grid: bool = False
    """Run the paper's whole grid: fine-tune off/on × saboteurs 0 and (--saboteurs or 0.5)."""

    def cost(self) -> Cost:
        """Estimated compute: every (setting, supply, trial) auction."""
        per_trial = sum(self._auction_cost(s) for s in study_settings(self))
        return Cost(per_trial * len(self.rarities) * self.trials, "trials")


@dataclass(frozen=True)
class ComparisonConfig(AuctionOptions):
    """The honest vs malicious comparison: the same auctions honest, compromised, screened."""

    rarities: Rarities = COMPARISON_RARITIES
    """Item supplies r; fish on sale = int(r · patrons)."""
    trials: Annotated[int, Field(ge=1, le=1000)] = 3
    """Independent auctions per supply and configuration."""
    saboteurs: Annotated[float, Field(gt=0, le=1)] = GRID_SABOTEURS
    """Fraction of saboteurs in the compromised configurations."""

    def cost(self) -> Cost:
        """Estimated compute: the three configurations' auctions."""
        per_trial = sum(self._auction_cost(s) for s in comparison_settings(self).values())
        return Cost(per_trial * len(self.rarities) * self.trials, "trials")


@dataclass(frozen=True)
class Setting:
    """One configuration of a study: who takes part and what the house does."""

    name: str
    fine_tune: bool
    saboteurs: float
    screen: bool


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
    key = np.random.SeedSequence([seed, round(rarity * 1_000_000), trial])
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
) -> Auction:
    """The patrons (not yet screened) and market config of one auction."""
    honest_rng, saboteur_rng, market_seed = auction_streams(seed, rarity, trial)
    n_saboteurs = int(setting.saboteurs * n_patrons)
    patrons = [
        honest_manifest(honest_rng, f"honest-{i:03d}", fine_tune=setting.fine_tune)
        for i in range(n_patrons - n_saboteurs)
    ]
    patrons += [saboteur_manifest(saboteur_rng, f"saboteur-{i:03d}") for i in range(n_saboteurs)]
    n_fish = fish_on_sale(n_patrons, rarity=rarity)
    market = MarketConfig(
        n_fish=n_fish,
        max_iterations=max_iterations,
        fine_tune=setting.fine_tune,
        fine_tune_rounds=fine_tune_rounds,
        seed=market_seed,
        evaluate_all_rows=False,
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


def _setting_name(fine_tune: bool, saboteurs: float, screen: bool) -> str:
    name = "honest" if saboteurs == 0 else f"saboteurs-{saboteurs:g}"
    return name + ("+fine-tune" if fine_tune else "") + ("+screened" if screen else "")


def study_settings(config: StudyConfig) -> list[Setting]:
    """The settings a study config asks for (one, or the grid's four)."""
    if not config.grid:
        combos = [(config.fine_tune, config.saboteurs)]
    else:
        share = config.saboteurs or GRID_SABOTEURS
        combos = [(ft, sab) for sab in (0.0, share) for ft in (False, True)]
    return [
        Setting(_setting_name(ft, sab, config.screen), ft, sab, config.screen) for ft, sab in combos
    ]


def settings_of(config: StudyConfig | ComparisonConfig) -> list[Setting]:
    """The settings a study or comparison config runs, in report order."""
    if isinstance(config, StudyConfig):
        return study_settings(config)
    return list(comparison_settings(config).values())


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
    _write_csv(path, [a.row for a in auctions])


def _write_csv(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in rows)


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_study(
    auctions: Sequence[AuctionResult], rows: Sequence[dict[str, Any]], out_dir: Path, seed: int
) -> list[str]:
    """Fig. C/D: price vs supply (every purchase a jittered dot, mean lines) and purchase rate
    vs supply (both definitions); one column per saboteur share. Returns the file names."""
    plt = _pyplot()
    jitter = np.random.default_rng(seed)
    shares = sorted({a.setting.saboteurs for a in auctions})
    colours = {True: "tab:red", False: "tab:blue"}
    files = []
    for kind in ("price", "rate"):
        fig, axes = plt.subplots(1, len(shares), figsize=(5.2 * len(shares), 4), squeeze=False)
        for ax, share in zip(axes[0], shares, strict=True):
            for fine_tune in (False, True):
                label = "fine-tune (Optim)" if fine_tune else "no fine-tune (noOptim)"
                mine = [r for r in rows if r["saboteurs"] == share and r["fine_tune"] == fine_tune]
                if not mine:
                    continue
                colour = colours[fine_tune]
                xs = [r["rarity"] for r in mine]
                if kind == "price":
                    for a in auctions:
                        if a.setting.saboteurs == share and a.setting.fine_tune == fine_tune:
                            prices = a.purchases
                            dx = jitter.uniform(-JITTER, JITTER, size=len(prices))
                            ax.scatter(a.rarity + dx, prices, s=4, alpha=0.25, color=colour)
                    ys = [math.nan if r["mean_price"] is None else r["mean_price"] for r in mine]
                    ax.plot(xs, ys, "-o", color=colour, label=label)
                    ax.set_ylabel("purchase price")
                else:
                    rates = [
                        math.nan if r["purchase_rate"] is None else r["purchase_rate"] for r in mine
                    ]
                    ax.plot(xs, rates, "-o", color=colour, label=f"sold / on sale, {label}")
                    ax.plot(
                        xs,
                        [r["buyer_fraction"] for r in mine],
                        "--s",
                        color=colour,
                        alpha=0.7,
                        label=f"buyers / patrons, {label}",
                    )
                    ax.set_ylabel("purchase rate")
                    ax.set_ylim(0, 1.05)
            title = "honest patrons" if share == 0 else f"{share:g} saboteurs"
            screened = any(a.setting.screen for a in auctions if a.setting.saboteurs == share)
            ax.set_title(title + (" (screened)" if screened else ""))
            ax.set_xlabel("item supply")
            ax.set_xlim(0, 1)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        fig.tight_layout()
        name = "price_vs_supply.png" if kind == "price" else "purchase_rate.png"
        fig.savefig(out_dir / name, dpi=110)
        plt.close(fig)
        files.append(name)
    return files


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
    auctions = auction_results(config, plan, payloads)
    progress(0.0, f"{len(auctions)} auctions")
    rows = summary_rows(auctions)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_results_csv(out_dir / "results.csv", auctions)
    figures = plot_study(auctions, rows, out_dir, config.seed)
    result = {
        "rows": rows,
        "auctions": len(auctions),
        "settings": [s.name for s in study_settings(config)],
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


def comparison_settings(config: ComparisonConfig) -> dict[str, Setting]:
    """honest, compromised and compromised+screened, on the same auctions."""
    ft = config.fine_tune
    return {
        "honest": Setting("honest", ft, 0.0, False),
        "compromised": Setting("compromised", ft, config.saboteurs, False),
        "compromised+screened": Setting("compromised+screened", ft, config.saboteurs, True),
    }


COMPARED = (
    ("mean_price", "mean purchase price"),
    ("purchase_rate", "purchase rate (sold / on sale)"),
    ("buyer_fraction", "buyer fraction (buyers / patrons)"),
    ("revenue", "revenue per auction"),
)


def plot_comparison(table: dict[str, list[dict[str, Any]]], path: Path) -> None:
    """Side by side: mean price, purchase rate, buyer fraction and revenue per supply."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(COMPARED), figsize=(4.2 * len(COMPARED), 3.6))
    styles = {"honest": "-o", "compromised": "-x", "compromised+screened": "--s"}
    for ax, (field, label) in zip(axes, COMPARED, strict=True):
        for name, rows in table.items():
            ys = [math.nan if r[field] is None else r[field] for r in rows]
            ax.plot([r["rarity"] for r in rows], ys, styles.get(name, "-"), label=name)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("item supply")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def assemble_comparison(
    config: ComparisonConfig,
    plan: Sequence[Unit],
    payloads: Sequence[Payload],
    *,
    out_dir: Path,
    progress: ProgressFn,
    watch: Stopwatch,
) -> dict[str, Any]:
    """The same auctions (same seeds) honest, compromised, and compromised but screened:
    results.csv, comparison.csv, comparison.png, summary.json; the --json object."""
    settings = comparison_settings(config)
    auctions = auction_results(config, plan, payloads)
    progress(0.0, f"{len(auctions)} auctions")
    rows = summary_rows(auctions)
    table = {name: [r for r in rows if r["setting"] == name] for name in settings}
    out_dir.mkdir(parents=True, exist_ok=True)
    write_results_csv(out_dir / "results.csv", auctions)
    _write_csv(out_dir / "comparison.csv", rows)
    plot_comparison(table, out_dir / "comparison.png")
    result = {
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
