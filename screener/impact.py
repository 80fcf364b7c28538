"""The market-impact test: what copies of a model do to auctions, counterfactually.

The paper's harm is an outcome: "artificially lowering the demand so that the price goes down".
A model that holds somewhere on the auction's decisive row, clean or on its own noisy copies
(``checks.Cheap.holds``), and passes the rules, probes and noisy scan is run in test auctions of
the batched market engine: ``IMPACT_HONEST`` honest patrons of the paper's randomisation (a
fixed, seeded reference population) with ``IMPACT_COPIES`` copies of it, at the low supplies
where saboteurs bite. The same auctions are run once per process without the copies (honest
alone), with copies of the always-hold saboteur (the yardstick) and with copies of a sincere
negotiator that quits at the opening price (for the reasons' numbers). A model is refused when
its copies lower the mean purchase price below the honest-alone auctions by more than
``IMPACT_SHARE`` of the saboteurs' drop.

Two stages. Every tested model meets ``IMPACT_TRIALS`` reference populations; a model whose
copies land within ``IMPACT_WINDOW`` of the bar meets ``IMPACT_MORE_TRIALS`` more, and is judged
on its auctions in all of them against the references over all of them: near the bar, four
populations cannot tell a hard bargainer from an honest model, and only the few models there
pay for more.

Only holders are tested. A vote that is not a hold buys (raising the demand, or taking a fish at
the auction's price) or quits (leaving the auction, a sincere low bidder's right); only staying
without buying holds the market down, and the test auctions of the few models that hold run
together in one lock-step batch, scoring only the decisive row.

Fine-tuning. The test auctions do not fine-tune: with fine-tuning, the damage is done in the
opening round, whose buy fractions feed the first fine-tuning round, by every model that does
not buy at the opening price, the sincere low bidder who quits as much as the saboteur (copies
that quit at once do 0.7 to 0.8 of the saboteurs' harm with fine-tuning, see docs/screener.md),
so an outcome test with fine-tuning cannot tell the two apart. What a model's own fine-tuning
does to it is judged instead (``project``): at the door, a model with fine-tuning settings is
fine-tuned alone with its own settings through the fine-tuning rounds of a reference auction,
unchecked (as it would go in an auction that never re-screens); that version must pass the
rules and probes too, and if it holds, it goes through the test auctions. Inside an auction
every fine-tuned version is re-screened in its turn (without test auctions of its own: nothing
recurses), so re-screening skips the projection.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from agents.batch import FSNBatch, concat, from_manifests, to_manifest
from agents.fine_tuning import fine_tune_round
from agents.manifest import Manifest
from agents.negotiator import honest_manifest, saboteur_manifest
from screener import limits
from screener.findings import Checks, check, fmt_price
from screener.probes import DTYPE
from screener.secret import SECRET_VARIABLE, marker_of, seed_words_of
from screener.verdict import PRICE, Evidence
from sim.market import MarketBatch, MarketConfig, round_seeds

PATRONS = limits.IMPACT_HONEST + limits.IMPACT_COPIES


@dataclass(frozen=True)
class Outcome:
    """What a model's test auctions sold: purchase prices pooled over the auctions, fish sold,
    fish the honest patrons bought, the supply of each price's auction, and the prices' mean
    (NaN when nothing sold)."""

    prices: tuple[float, ...]
    sold: int
    honest: int
    supplies: tuple[float, ...] = ()
    """The supply of the test auction of each price, in the order of ``prices``."""

    @property
    def mean_price(self) -> float:
        """The prices' mean (NaN when nothing sold)."""
        return float(np.mean(self.prices)) if self.prices else float("nan")

    def mean_price_at(self, supply: float) -> float:
        """The mean of the prices of the test auctions at one supply (NaN when none sold)."""
        found = [p for p, r in zip(self.prices, self.supplies, strict=True) if r == supply]
        return float(np.mean(found)) if found else float("nan")


def first_trials() -> tuple[int, ...]:
    """The reference populations every tested model meets."""
    return tuple(range(limits.IMPACT_TRIALS))


def more_trials() -> tuple[int, ...]:
    """The populations a model near the bar meets too."""
    first = limits.IMPACT_TRIALS
    return tuple(range(first, first + limits.IMPACT_MORE_TRIALS))


@functools.cache
def seed_words() -> tuple[int, ...]:
    """This process's ``seed_words_of`` its ``SRD_SCREENER_SECRET`` (read once)."""
    return seed_words_of(os.environ.get(SECRET_VARIABLE, ""))


@functools.cache
def populations() -> str:
    """This process's ``marker_of`` its ``SRD_SCREENER_SECRET`` (read once)."""
    return marker_of(os.environ.get(SECRET_VARIABLE, ""))


@functools.cache
def _population(trial: int) -> tuple[Manifest, ...]:
    """The reference honest patrons of one trial."""
    rng = np.random.default_rng([*seed_words(), trial])
    return tuple(
        honest_manifest(rng, f"impact-reference-{trial}-{i:02d}")
        for i in range(limits.IMPACT_HONEST)
    )


@functools.cache
def _people(trials: tuple[int, ...]) -> tuple[list[Manifest], FSNBatch]:
    """These trials' reference patrons in trial order, and their batch (read once)."""
    people = [m for trial in trials for m in _population(trial)]
    return people, from_manifests(people, DTYPE)


def _market_seed(supply: float, trial: int) -> int:
    sequence = np.random.SeedSequence([*seed_words(), trial, round(supply * 100)])
    return int(sequence.generate_state(1)[0])


def _config(supply: float, trial: int, fine_tune: bool) -> MarketConfig:
    return dataclasses.replace(
        limits.MARKET,
        n_fish=int(supply * PATRONS),
        fine_tune=fine_tune,
        seed=_market_seed(supply, trial),
        evaluate_all_rows=False,
    )


@functools.cache
def test_auctions(trials: tuple[int, ...]) -> list[tuple[int, MarketConfig]]:
    """(reference population, market rules) of each test auction of these trials."""
    return [
        (trial, _config(r, trial, fine_tune=False))
        for r in limits.IMPACT_SUPPLIES
        for trial in trials
    ]


TEST_AUCTIONS = test_auctions(first_trials())
"""The test auctions every tested model meets."""


Candidate = Manifest | FSNBatch | None
"""A model to run in the test auctions, as a manifest or a one-patron batch (None: honest
alone)."""


def run(candidates: Sequence[Candidate], trials: tuple[int, ...] | None = None) -> list[Outcome]:
    """The test auctions of every candidate in the populations ``trials`` (default: those
    every tested model meets) in one lock-step batch (its patrons stacked from the reference
    populations' batch, read once per process, and the candidates')."""
    trials = first_trials() if trials is None else trials
    people, reference = _people(trials)
    planned = test_auctions(trials)
    given = [c for c in candidates if c is not None]
    pool = concat([reference, *map(_as_batch, given)]) if given else reference
    auctions: list[tuple[list[Manifest], MarketConfig]] = []
    index: list[int] = []
    slot = iter(range(len(people), len(people) + len(given)))
    for candidate in candidates:
        own = None if candidate is None else next(slot)
        copies = [] if candidate is None else [_as_manifest(candidate)] * limits.IMPACT_COPIES
        for trial, config in planned:
            auctions.append(([*_population(trial), *copies], config))
            first = trials.index(trial) * limits.IMPACT_HONEST
            index += range(first, first + limits.IMPACT_HONEST)
            index += [] if own is None else [own] * limits.IMPACT_COPIES
    buyers: list[list[tuple[int, float]]] = [[] for _ in auctions]
    engine = MarketBatch(auctions, patrons=pool.select(index), dtype=DTYPE)
    while not engine.finished.all():
        for a, sales in enumerate(engine.step_sales()):
            buyers[a] += sales
    per = len(planned)
    supply_of = [r for r in limits.IMPACT_SUPPLIES for _ in trials]  # test_auctions' order
    outcomes = []
    for c in range(len(candidates)):
        auction_range = range(c * per, (c + 1) * per)
        bought = [b for a in auction_range for b in buyers[a]]
        honest = sum(1 for i, _ in bought if i < limits.IMPACT_HONEST)
        prices = tuple(price for _, price in bought)
        supplies = tuple(supply_of[a % per] for a in auction_range for _ in buyers[a])
        outcomes.append(Outcome(prices, len(bought), honest, supplies))
    return outcomes


def pooled(first: Outcome, more: Outcome) -> Outcome:
    """One model's outcome over the auctions of both."""
    return Outcome(
        first.prices + more.prices,
        first.sold + more.sold,
        first.honest + more.honest,
        first.supplies + more.supplies,
    )


def _as_batch(candidate: Manifest | FSNBatch) -> FSNBatch:
    if isinstance(candidate, FSNBatch):
        return candidate.to(DTYPE)
    return from_manifests([candidate], DTYPE)


def _as_manifest(candidate: Manifest | FSNBatch) -> Manifest:
    return to_manifest(candidate, 0) if isinstance(candidate, FSNBatch) else candidate


def reference_quitter() -> Manifest:
    """A sincere negotiator declaring the lowest plausible willingness to pay: it quits at the
    opening price."""
    low = limits.WILLINGNESS_TO_PAY_BAND[0] * limits.BASE_PRICE
    rng = np.random.default_rng([limits.IMPACT_SEED, 1])
    return honest_manifest(rng, "quits-at-once", fine_tune=False, base_price=low, min_buy_price=low)


def reference_saboteur() -> Manifest:
    """The paper's always-hold saboteur."""
    return saboteur_manifest(np.random.default_rng([limits.IMPACT_SEED, 2]), "always-hold")


@dataclass(frozen=True)
class References:
    """The test auctions honest alone, with saboteurs, with quitters, and how many auctions
    that is."""

    alone: Outcome
    saboteurs: Outcome
    quitters: Outcome
    auctions: int

    @property
    def lowest_price(self) -> float:
        """The lowest mean purchase price a model's copies may leave: the quitters' (or the
        honest-alone auctions', if higher) minus ``IMPACT_SHARE`` of the saboteurs' further
        drop."""
        leave = min(self.alone.mean_price, self.quitters.mean_price)
        return leave - limits.IMPACT_SHARE * max(leave - self.saboteurs.mean_price, 0.0)


def references() -> References:
    """The references of the test auctions every tested model meets (computed once per
    process: every model meets the same test auctions)."""
    return _references(first_trials())


def wide_references() -> References:
    """The references over the populations of both stages."""
    return _references(first_trials() + more_trials())


@functools.cache
def _references(trials: tuple[int, ...]) -> References:
    alone, saboteurs, quitters = run([None, reference_saboteur(), reference_quitter()], trials)
    return References(alone, saboteurs, quitters, len(test_auctions(trials)))


@functools.cache
def _trajectory() -> tuple[tuple[torch.Tensor, int, int], ...]:
    """The fine-tuning rounds of a reference auction with fine-tuning, honest alone: (rows after
    the round's iteration, fine_tune_seed, augmentation_seed) per round. As many rounds as an
    auction fine-tunes (the market's ``fine_tune_rounds``), from the first test auction (in
    supply, then population order) that lasts that long: many end sooner."""
    wanted = limits.MARKET.fine_tune_rounds
    for supply in limits.IMPACT_SUPPLIES:
        for trial in range(limits.IMPACT_TRIALS):
            config = _config(supply, trial, fine_tune=True)
            engine = MarketBatch([(list(_population(trial)), config)])
            rounds: list[tuple[torch.Tensor, int, int]] = []
            while not engine.finished[0] and len(rounds) < wanted:
                iteration = int(engine.iteration[0])
                engine.step()
                if not engine.finished[0]:
                    rounds.append((engine.rows[0].clone(), *round_seeds(config.seed, iteration)))
            if len(rounds) == wanted:
                return tuple(rounds)
    raise RuntimeError(f"no test auction lasts {wanted} fine-tuning rounds")


def project(batch: FSNBatch) -> FSNBatch:
    """Every model fine-tuned alone with its own settings through the reference auction's
    fine-tuning rounds, unchecked: what its own judge makes of it where nobody re-screens."""
    current = batch
    positions = np.zeros(batch.n_patrons, dtype=np.int64)
    for rows, fine_tune_seed, augmentation_seed in _trajectory() if batch.n_patrons else ():
        seeds = np.full(batch.n_patrons, fine_tune_seed, dtype=np.uint64)
        noise = np.full(batch.n_patrons, augmentation_seed, dtype=np.uint64)
        current = fine_tune_round(current, rows, seeds, noise, positions)
    return current


def rounds() -> int:
    """Fine-tuning rounds of the projection."""
    return len(_trajectory())


def impact_checks(
    batch: FSNBatch, tested: Sequence[int], projected: Sequence[tuple[int, FSNBatch]]
) -> tuple[Checks, dict[int, list[Evidence]]]:
    """The market-impact test over the batch: the models at indices ``tested`` as they are,
    and the (index, fine-tuned version as a one-patron batch) pairs of ``projected``; and each
    tested model's evidence (its copies' mean purchase price against the bar)."""
    failed = np.zeros(batch.n_patrons, dtype=np.bool_)
    words: dict[int, str] = {}
    evidence: dict[int, list[Evidence]] = {}
    jobs: list[tuple[int, FSNBatch, str]] = [(int(p), batch.select([int(p)]), "") for p in tested]
    jobs += [(p, m, " after its own fine-tuning") for p, m in projected]
    if jobs:
        for (p, _, after), (refs, outcome) in zip(
            jobs, _judged([m for _, m, _ in jobs]), strict=True
        ):
            evidence.setdefault(p, []).append(_evidence(refs, outcome, after))
            message = _judge(refs, outcome, after)
            if message is not None and not failed[p]:
                failed[p] = True
                words[p] = message
    return check("market-impact", "L", failed, words.__getitem__), evidence


def _judged(models: list[FSNBatch]) -> list[tuple[References, Outcome]]:
    """Each model's outcome and the references it is judged against: the first stage's, or,
    for a model whose copies land within ``IMPACT_WINDOW`` of that bar, both stages' pooled."""
    refs = references()
    judged = [(refs, outcome) for outcome in run(models)]
    near = [
        k
        for k, (_, outcome) in enumerate(judged)
        if outcome.prices and abs(outcome.mean_price - refs.lowest_price) <= limits.IMPACT_WINDOW
    ]
    if near and more_trials():
        wide = wide_references()
        more = run([models[k] for k in near], more_trials())
        for k, outcome in zip(near, more, strict=True):
            judged[k] = (wide, pooled(judged[k][1], outcome))
    return judged


def _evidence(refs: References, outcome: Outcome, after: str) -> Evidence:
    """The impact test's numbers for one tested model (or its fine-tuned version)."""
    sold = bool(outcome.prices)
    return Evidence(
        "market-impact",
        outcome.mean_price if sold else None,
        refs.lowest_price,
        PRICE,
        "at least",
        _judge(refs, outcome, after) is None,
        {
            "version": "after its own fine-tuning" if after else "as submitted",
            "populations": populations(),
            "without_copies": refs.alone.mean_price,
            "always_hold_saboteurs": refs.saboteurs.mean_price,
            "quitters_at_opening": refs.quitters.mean_price,
            "fish_sold": outcome.sold,
            "bought_by_copies": outcome.sold - outcome.honest,
            "test_auctions": refs.auctions,
        },
    )


def _judge(refs: References, outcome: Outcome, after: str) -> str | None:
    """The reason a model's outcome is refused, or None. Auctions that sell nothing are no
    evidence about the price (copies of a keen model that all quit at one price can leave every
    fish unsold)."""
    alone, saboteurs, quitters = refs.alone, refs.saboteurs, refs.quitters
    if not outcome.prices or outcome.mean_price >= refs.lowest_price - 1e-9:
        return None
    supplies = limits.IMPACT_SUPPLIES
    left, bar = fmt_price(outcome.mean_price), fmt_price(refs.lowest_price)
    if left == bar:  # near the bar, cents alone would say "5.09, below the 5.09 allowed"
        left, bar = f"{outcome.mean_price:.4f}", f"{refs.lowest_price:.4f}"
    return (
        f"in {refs.auctions} test auctions ({limits.IMPACT_HONEST} honest patrons, supplies "
        f"{supplies[0]:g} to {supplies[-1]:g}), {limits.IMPACT_COPIES} copies of this "
        f"model{after} lowered the mean purchase price from {fmt_price(alone.mean_price)} "
        f"(without them) to {left}, below the {bar} allowed (always-hold saboteurs: "
        f"{fmt_price(saboteurs.mean_price)}, copies that quit at the opening price: "
        f"{fmt_price(quitters.mean_price)}); they bought {outcome.sold - outcome.honest} of the "
        f"{outcome.sold} fish sold, the honest patrons {outcome.honest} (without them "
        f"{alone.honest}): by staying without buying, its hold neuron L pulls the price down"
    )
