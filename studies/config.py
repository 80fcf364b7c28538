"""What an auction study is asked: its knobs (``StudyConfig``, ``ComparisonConfig``), the
settings they span, and their estimated compute."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

from pydantic import Field

from agents.negotiator import WILLINGNESS_TO_PAY_RANGE
from sim.experiment import Cost, distinct
from sim.market import BuyFractionRule, MarketConfig
from sim.market.config import raises_by_a_decrement

PAPER_RARITIES = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
"""The paper's item supplies."""
COMPARISON_RARITIES = (0.1, 0.3, 0.5, 0.7, 0.9)
"""The comparison's default supplies (small enough for the demo)."""
GRID_SABOTEURS = 0.5
"""The saboteur fraction of the grid's and the comparison's compromised auctions."""
Rarity = Annotated[float, Field(gt=0, le=1)]


SUPPLY_PARTS = 1_000_000
"""Supplies are told apart to a millionth: an auction's random streams are keyed by its supply
in millionths (``studies.auctions.auction_streams``), so two supplies closer than that would
play the same auctions."""


def supply_key(rarity: float) -> int:
    """A supply in millionths: what keys its auctions' random streams."""
    return round(rarity * SUPPLY_PARTS)


Rarities = Annotated[
    tuple[Rarity, ...],
    Field(min_length=1, max_length=100, json_schema_extra={"uniqueItems": True}),
    distinct(
        "supply",
        "more trials: raise trials",
        key=supply_key,
        apart=" (supplies are told apart to a millionth)",
    ),
]
AUCTION_COST_S = 0.01
"""Compute of one auction of 64 patrons without fine-tuning, for the job budget: about twice
the lock-step engine's measured cost per auction."""
FINE_TUNED_AUCTION_COST_S = 0.05
"""The same with fine-tuning (measured about 0.02 s per auction)."""
SCREENING_COST_S = 0.01
"""Screening one patron (the behavioural tests included), with a margin."""
ITERATION_COST_S = 1e-4
"""One iteration of an auction of 64 patrons (measured 70 µs): an auction that plays to its
``max_iterations`` (price rules that never reach a stalemate) costs that many."""


@dataclass(frozen=True)
class AuctionOptions:
    """What every auction of a study shares (the study configs add their grid)."""

    SCHEMA_RULES: ClassVar[tuple[dict[str, Any], ...]] = (
        {  # fine-tuning's own options belong to a run that fine-tunes (a grid runs both)
            "if": {
                "anyOf": [
                    {"properties": {"fine_tune": {"const": True}}, "required": ["fine_tune"]},
                    {"properties": {"grid": {"const": True}}, "required": ["grid"]},
                ]
            },
            "then": {"properties": {"fine_tune_rounds": {"minimum": 1}}},
            "else": {
                "not": {"anyOf": [{"required": ["fine_tune_rounds"]}, {"required": ["freeze_pfc"]}]}
            },
        },
    )
    """``problems``'s rule across options, as JSON Schema (``sim.experiment.config_schema``)."""

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
    buy_fraction: BuyFractionRule = MarketConfig.buy_fraction
    """Whom each row's buy fraction f counts: all (every voter, the paper's) or staying (buyers
    and holders: quitting does not lower f)."""
    rows: Annotated[int, Field(ge=1, le=256)] = MarketConfig.n_rows
    """Item rows each patron scores per iteration: the prototype and its variations (64, the
    reference's, made the paper's figures; the paper's text says 16)."""
    base_price: Annotated[float, Field(gt=0, le=1000)] = MarketConfig.base_price
    """Every auction's starting price (and its prototype fish's), and the top of the patrons'
    willingness to pay b ~ U(min_buy_price, base_price) (the reference's --base_price)."""
    min_buy_price: Annotated[float, Field(gt=0, le=1000)] = WILLINGNESS_TO_PAY_RANGE[0]
    """The bottom of the patrons' willingness to pay (the reference's --min_buy_price)."""
    threshold_sell_price: Annotated[float, Field(ge=0, le=1000)] = MarketConfig.threshold_sell_price
    """The initial stalemate threshold: an auction stops once its price falls below it."""
    increment: Annotated[float, Field(gt=0, le=1000)] = MarketConfig.increment
    """High demand raises the price by increment − U(0, 4)·decrement."""
    decrement: Annotated[float, Field(gt=0, le=1000)] = MarketConfig.decrement
    """Low demand lowers the price by this."""
    freeze_pfc: bool = False
    """Fine-tuning leaves every patron's judge (PFC) as built: its ``pfc.trainable`` is false
    (the reference trains it with the rest, which made the figures)."""

    def problems(self, given: frozenset[str] = frozenset()) -> list[dict[str, str]]:
        """Options that contradict each other (each named), and options ``given`` (named by
        the user) that change nothing: fine-tuning's own with no fine-tuning, no fine-tuning
        rounds with fine-tuning on. A supply that puts no fish on sale (int(rarity × patrons)
        = 0, as 0.1 of fewer than 10 patrons) is not one: its auctions run as the reference
        runs them (they stop at once, sold out) and its row says ``n_fish`` 0,
        ``purchase_rate`` and ``mean_price`` null."""
        problems = []
        tunes = self.fine_tune or bool(getattr(self, "grid", False))  # the grid runs both
        for name in ("fine_tune_rounds", "freeze_pfc"):
            if name in given and not tunes:
                problems.append(
                    {
                        "field": name,
                        "message": "without fine-tune nothing is fine-tuned: it does not take "
                        + name.replace("_", "-"),
                    }
                )
        if tunes and self.fine_tune_rounds == 0:
            problems.append(
                {
                    "field": "fine_tune_rounds",
                    "message": "0 rounds fine-tune nothing: give at least 1, or leave "
                    "fine-tune off",
                }
            )
        if self.min_buy_price > self.base_price:
            problems.append(
                {
                    "field": "min_buy_price",
                    "message": f"{self.min_buy_price:g} is above base_price {self.base_price:g}: "
                    "the willingness to pay is drawn between the two",
                }
            )
        if not raises_by_a_decrement(self.increment, self.decrement):
            problems.append(
                {
                    "field": "increment",
                    "message": f"{self.increment:g} is below 5 × decrement ({self.decrement:g}): "
                    "a raise of increment − U(0, 4)·decrement could be negative",
                }
            )
        return problems

    def _auction_cost(self, setting: Setting) -> float:
        """Estimated compute of one auction of ``setting``: its iterations, as many as
        ``max_iterations`` allows (the default rules end most auctions in a few dozen, sold out
        or at a stalemate, but rules can be set that never do), with fine-tuning (and the
        re-screening that follows it) growing with the rounds it runs, beyond the default's
        four."""
        per_auction = max(AUCTION_COST_S, self.max_iterations * ITERATION_COST_S)
        screenings = 1.0
        if setting.fine_tune:
            rounds = min(self.fine_tune_rounds, self.max_iterations)
            scale = max(rounds, MarketConfig.fine_tune_rounds) / MarketConfig.fine_tune_rounds
            per_auction += (FINE_TUNED_AUCTION_COST_S - AUCTION_COST_S) * scale
            screenings = scale
        per_auction *= max(self.rows, MarketConfig.n_rows) / MarketConfig.n_rows
        screening = SCREENING_COST_S * screenings if setting.screen else 0.0
        return self.patrons * (per_auction / 64 + screening)


@dataclass(frozen=True)
class StudyConfig(AuctionOptions):
    """Fish sale auctions without HTTP: purchase price and rate against item supply.

    The paper's Fig. C/D grid (``srd auction-study``)."""

    SCHEMA_RULES: ClassVar[tuple[dict[str, Any], ...]] = (
        *AuctionOptions.SCHEMA_RULES,
        {  # a grid compares no saboteurs with some
            "if": {"properties": {"grid": {"const": True}}, "required": ["grid"]},
            "then": {"properties": {"saboteurs": {"exclusiveMinimum": 0}}},
        },
    )

    rarities: Rarities = PAPER_RARITIES
    """Supply: fish on sale per patron (r, the paper's rarity); fish on sale = int(r · patrons)."""
    trials: Annotated[int, Field(ge=1, le=1000)] = 10
    """Independent auctions per supply (and per setting)."""
    saboteurs: Annotated[float, Field(ge=0, le=1)] = 0.0
    """Fraction of the patrons that are always-hold saboteurs (the last ones)."""
    screen: bool = False
    """Screen every patron before the auction (refused ones stay out) and re-screen fine-tuned
    patrons after each round (refused versions are reverted)."""
    grid: bool = False
    """Run the paper's whole grid: fine-tune off/on × saboteurs 0 and (--saboteurs or 0.5)."""

    def problems(self, given: frozenset[str] = frozenset()) -> list[dict[str, str]]:
        """``AuctionOptions.problems``, and a grid given 0 saboteurs (its compromised half
        would be its honest half)."""
        found = super().problems(given)
        if self.grid and "saboteurs" in given and self.saboteurs == 0:
            found.append(
                {
                    "field": "saboteurs",
                    "message": "the grid compares no saboteurs with this share of them: give a "
                    f"share above 0 (without it, {GRID_SABOTEURS:g})",
                }
            )
        return found

    def cost(self) -> Cost:
        """Estimated compute: every (setting, supply, trial) auction."""
        per_trial = sum(self._auction_cost(s) for s in study_settings(self))
        return Cost(per_trial * len(self.rarities) * self.trials, "trials")


@dataclass(frozen=True)
class ComparisonConfig(AuctionOptions):
    """Honest vs malicious: the same auctions with and without saboteurs, screened or not.

    ``srd comparison``: honest patrons only, unscreened and screened (what screening costs an
    honest market); with ``saboteurs`` of them always-hold saboteurs, unscreened and screened;
    and the compromised population's honest patrons without its saboteurs (honest-alone: what
    screening restores)."""

    rarities: Rarities = COMPARISON_RARITIES
    """Supply: fish on sale per patron (r, the paper's rarity); fish on sale = int(r · patrons)."""
    trials: Annotated[int, Field(ge=1, le=1000)] = 3
    """Independent auctions per supply and configuration."""
    saboteurs: Annotated[float, Field(gt=0, le=1)] = GRID_SABOTEURS
    """Fraction of saboteurs in the compromised configurations."""

    def cost(self) -> Cost:
        """Estimated compute: the five configurations' auctions."""
        per_trial = sum(self._auction_cost(s) for s in comparison_settings(self).values())
        return Cost(per_trial * len(self.rarities) * self.trials, "trials")


@dataclass(frozen=True)
class Setting:
    """One configuration of a study: who takes part and what the house does."""

    name: str
    fine_tune: bool
    saboteurs: float
    screen: bool
    alone: bool = False
    """The population's honest patrons only: its saboteurs stay out (the fish are those of
    the whole population)."""


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


def comparison_settings(config: ComparisonConfig) -> dict[str, Setting]:
    """honest, honest+screened, compromised, compromised+screened and honest-alone, on the
    same auctions."""
    ft = config.fine_tune
    return {
        "honest": Setting("honest", ft, 0.0, False),
        "honest+screened": Setting("honest+screened", ft, 0.0, True),
        "compromised": Setting("compromised", ft, config.saboteurs, False),
        "compromised+screened": Setting("compromised+screened", ft, config.saboteurs, True),
        "honest-alone": Setting("honest-alone", ft, config.saboteurs, False, alone=True),
    }


def saboteur_count(share: float, n_patrons: int) -> int:
    """Saboteurs among ``n_patrons`` for a share of them: the patrons after the first
    ``int((1 - share) · n)`` honest ones, the reference's split (its first ``int(n/2)`` patrons
    honest, the rest saboteurs: 32 of 63 at a half). Rounded to 9 places first, so that a share
    like 0.9 of 10 leaves 1 honest patron, not the 0 that ``0.0999…98 · 10`` would."""
    return n_patrons - math.floor(round((1 - share) * n_patrons, 9))


def comparison_caption(config: ComparisonConfig) -> str:
    """What each line of the comparison figure is: one sentence per configuration, one line
    each."""
    n_saboteurs = saboteur_count(config.saboteurs, config.patrons)
    n_honest = config.patrons - n_saboteurs
    tuned = "fine-tuning" if config.fine_tune else "no fine-tuning"
    return "\n".join(
        (
            f"honest: {config.patrons} honest patrons, no screening ({tuned}, f counts "
            f"{config.buy_fraction} voters).",
            "honest+screened: the honest patrons screened before the auction, the refused "
            "staying out: what screening costs an honest market.",
            f"compromised: the same auctions with the last {n_saboteurs} of the "
            f"{config.patrons} patrons always-hold saboteurs, no screening.",
            "compromised+screened: the compromised patrons screened before the auction, the "
            "refused staying out.",
            f"honest-alone: the compromised population's {n_honest} honest patrons without its "
            "saboteurs, the same fish and seeds: what screening restores.",
        )
    )
