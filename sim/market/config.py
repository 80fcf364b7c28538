"""An auction's rules (``MarketConfig``) and the questions the engine asks of them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from agents.negotiator import BASE_PRICE

FineTuneMode = Literal["server", "remote"]
"""Who runs a fine-tuning round: the market itself, or the patrons elsewhere."""
BuyFractionRule = Literal["all", "staying"]
"""Whom a row's buy fraction f counts: every voter (the paper's), or buyers and holders only."""


@dataclass(frozen=True)
class MarketConfig:
    """One auction's rules (defaults: the reference's)."""

    n_fish: int
    """Fish on sale (``fish_on_sale``: given, or int(rarity · patrons))."""
    max_iterations: int = 64
    """Iterations at most."""
    base_price: float = BASE_PRICE
    """Starting price, also the prototype fish's price (the design's base item)."""
    threshold_sell_price: float = 4.8
    """Initial stalemate threshold: stop once the price falls below it."""
    increment: float = 0.05
    """High demand raises the price by increment − U(0, 4)·decrement."""
    decrement: float = 0.01
    """Low demand lowers the price by this."""
    n_rows: int = 64
    """Item rows: row 0 the prototype, the others perturbed variations."""
    fine_tune: bool = False
    """Let patrons fine-tune themselves (SRD) with their own settings."""
    fine_tune_rounds: int = 4
    """Fine-tuning happens after each of the first this-many iterations (reference: 5)."""
    fine_tune_mode: FineTuneMode = "server"
    """"server": the market fine-tunes the patrons; "remote": each round is left pending for
    the patrons to fine-tune themselves, and ``apply_round`` takes their results."""
    buy_fraction: BuyFractionRule = "all"
    """f of a row = its buy votes / "all" its votes (the paper's), or / its buy and hold votes
    ("staying": quitters do not lower f; 0 when nobody stays)."""
    seed: int = 0
    """Seeds the rows, the augmentation noise, the shuffles and the price raises."""
    evaluate_all_rows: bool = True
    """False: rows 1.. are scored only while their votes can still feed a fine-tuning round
    (the auction is the same — row 0 alone decides and its noise has its own generator — but
    ``row_votes`` then counts row 0 only afterwards)."""

    def __post_init__(self) -> None:
        problems = []
        if self.n_fish < 0:
            problems.append("n_fish must be ≥ 0")
        if self.max_iterations < 1:
            problems.append("max_iterations must be ≥ 1")
        if self.n_rows < 1:
            problems.append("n_rows must be ≥ 1")
        if self.decrement <= 0 or not raises_by_a_decrement(self.increment, self.decrement):
            problems.append("need decrement > 0 and increment ≥ 5·decrement (a raise > 0)")
        if self.fine_tune_rounds < 0:
            problems.append("fine_tune_rounds must be ≥ 0")
        if self.seed < 0:
            problems.append("seed must be ≥ 0")
        if self.fine_tune_mode not in get_args(FineTuneMode):
            problems.append(f"fine_tune_mode must be one of {get_args(FineTuneMode)}")
        if self.buy_fraction not in get_args(BuyFractionRule):
            problems.append(f"buy_fraction must be one of {get_args(BuyFractionRule)}")
        if problems:
            raise ValueError("; ".join(problems))


def raises_by_a_decrement(increment: float, decrement: float) -> bool:
    """Whether ``increment`` ≥ 5·``decrement``, so that a raise (the increment less up to 4
    decrements) is at least a decrement; up to a part in 10¹² below counts (``decrement`` sent
    as ``increment / 5`` comes back a bit above it)."""
    return increment >= 5 * decrement * (1 - 1e-12)


def fish_on_sale(n_patrons: int, *, n_fish: int | None = None, rarity: float | None = None) -> int:
    """The fish an auction of ``n_patrons`` puts on sale: ``n_fish`` as given, or the supply
    ``rarity`` as int(rarity · patrons) (truncated, as the reference). Exactly one of the two
    is given (ValueError otherwise); the result may be 0 when rarity · patrons < 1."""
    if (n_fish is None) == (rarity is None):
        raise ValueError("give exactly one of n_fish or rarity")
    if n_fish is not None:
        return n_fish
    assert rarity is not None
    return int(rarity * n_patrons)


def scores_all_rows(config: MarketConfig, iteration: int) -> bool:
    """Whether rows 1.. are scored in this iteration."""
    return config.evaluate_all_rows or (config.fine_tune and iteration < config.fine_tune_rounds)


def fine_tunes_after(config: MarketConfig, iteration: int) -> bool:
    """Whether patrons fine-tune after this iteration (if the auction goes on)."""
    return config.fine_tune and iteration < config.fine_tune_rounds
