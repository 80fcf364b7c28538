"""The fish sale auction (paper, "Fish Sale Auction"; docs/auction.md) as a pure
engine: no HTTP, no database. It advances one iteration at a time and reports each as an
``IterationRecord`` so a caller can persist or stream it; ``checkpoint``/``restore`` continue
an interrupted auction bit for bit.

One iteration (all patrons evaluated in one batched tensor pass):

1. Every active patron scores the item rows (the prototype fish at the current price, row 0,
   and its perturbed variations) and votes buy / hold / quit on each. Only row 0 decides:
   N_buy = number of row-0 buy votes.
2. High demand, N_buy > N_available: nobody buys; the stalemate threshold becomes
   price + decrement and the price rises by increment − u·decrement, u ~ U(0, 4).
   Low demand: every row-0 buyer buys at the current price; the price falls by decrement.
3. Each row's f (buy fraction) becomes the fraction of this round's voters who voted buy on
   that row. Row-0 quitters leave.
4. Stop when sold out, when no patron is left, at a stalemate (price < threshold) or after
   ``max_iterations``. Otherwise, in the first ``fine_tune_rounds`` iterations and if
   ``fine_tune``, every active patron fine-tunes itself (SRD) on the updated rows: in the
   market (``fine_tune_mode`` "server"), or elsewhere ("remote": the iteration leaves a
   ``FineTuneRound`` pending, and ``apply_round`` brings the patrons' results back before the
   next iteration).

A fine-tuning round's randomness is each patron's own: the round's ``fine_tune_seed`` (row
shuffles) and ``augmentation_seed`` (the noise of the D_ic copies) come from the auction seed
and the iteration (``round_seeds``), and each patron derives its generators from them and its
position in the auction (``agents.fine_tuning.fine_tune_round``). So a patron fine-tuning alone
(a remote agent given the round's rows and seeds) computes what the market would.

``MarketBatch`` runs many independent auctions in lock-step (the study's grid); ``Market`` is
one auction. Each auction draws only from its own generators, derived from its seed, so it is
the same auction alone or in a batch.
"""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import numpy as np
import torch
from torch import Tensor

from agents.batch import FSNBatch, from_manifests, to_manifest
from agents.fine_tuning import derive_seeds, fine_tune_round
from agents.forward import ACTIONS, decide, noise_scale, standard_normal
from agents.manifest import INPUTS, Manifest
from agents.negotiator import BASE_ITEM, BASE_PRICE

Rescreen = Callable[[int, Manifest], bool]
"""Called as ``rescreen(patron_index, fine_tuned_manifest)``; False reverts that patron."""
RescreenBatch = Callable[[FSNBatch], np.ndarray]
"""Called once per fine-tuning round with every fine-tuned patron of the batch's auctions (a
sub-batch, in batch order); returns one bool per patron, False reverts it."""

SIZE_JITTER = 0.2
"""Rows 1..: length, weight and gill colour each get + U(−0.2, 0.2) (the reference's rows)."""
SUBTYPE_MINORITY = 0.2
"""Rows 1..: each sub-type flag is −½ with probability 0.2, else +½ (the reference's rows)."""
PRICE, BUY_FRACTION = INPUTS.index("price"), INPUTS.index("buy_fraction")
STOP_REASONS = ("sold_out", "no_patrons", "stalemate", "max_iterations")
EVALUATION_CHUNK = 32_000
"""(patron, row, copy) evaluations per ``decide`` call: bigger tensors fall out of the cache
(3–5× slower per evaluation at 1.8M)."""
FineTuneMode = Literal["server", "remote"]
"""Who runs a fine-tuning round: the market itself, or the patrons elsewhere."""
FINE_TUNE_STREAM, AUGMENTATION_STREAM = 1, 2
"""Children of an iteration's seed: the round's shuffle seed and its augmentation seed."""
CHECKPOINT_FORMAT = 2
"""``MarketBatch.state()`` format; 2 adds the pending remote rounds (1 is read as none)."""


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
        if self.decrement <= 0 or self.increment < 5 * self.decrement:
            problems.append("need decrement > 0 and increment ≥ 5·decrement (a raise > 0)")
        if self.fine_tune_rounds < 0:
            problems.append("fine_tune_rounds must be ≥ 0")
        if self.seed < 0:
            problems.append("seed must be ≥ 0")
        if self.fine_tune_mode not in get_args(FineTuneMode):
            problems.append(f"fine_tune_mode must be one of {get_args(FineTuneMode)}")
        if problems:
            raise ValueError("; ".join(problems))


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


@dataclass
class IterationRecord:
    """What happened in one iteration of one auction."""

    iteration: int
    price: float
    """Price at the start of the iteration (what the votes were about)."""
    n_available: int
    """Fish available at the start of the iteration."""
    votes: dict[str, int]
    """Row-0 decisions of the patrons active this round: {"buy", "hold", "quit"}."""
    row_votes: dict[str, int]
    """The same over every scored row (what feeds the f column)."""
    buyers: list[tuple[int, float]]
    """(patron index, purchase price) of this iteration's purchases."""
    quitters: list[int]
    """Patron indices that quit this iteration."""
    next_price: float
    n_available_after: int
    finished: bool
    stop_reason: str | None
    """sold_out | no_patrons | stalemate | max_iterations, once finished."""
    fine_tuned: list[int] = field(default_factory=list)
    """Patrons whose fine-tuned parameters were kept after this iteration."""
    reverted: list[int] = field(default_factory=list)
    """Patrons whose fine-tuned parameters the re-screening refused (reverted)."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        out = dataclasses.asdict(self)
        out["buyers"] = [{"patron": p, "price": price} for p, price in self.buyers]
        return out


@contextmanager
def single_thread() -> Iterator[None]:
    """Run torch on one thread inside the block: the auction's tensors are small, and
    intra-op threads only add contention (3× slower on a busy 2-core machine)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def item_rows(config: MarketConfig, rng: np.random.Generator) -> np.ndarray:
    """The R item rows (the reference's): row 0 the design's base item at the config's base
    price; rows 1.. with jittered length, weight, gill and re-drawn sub-types. f starts at ½
    everywhere."""
    prototype = [BASE_ITEM[name] for name in INPUTS]
    prototype[PRICE] = config.base_price
    rows = np.tile(np.array(prototype, dtype=np.float64), (config.n_rows, 1))
    extra = config.n_rows - 1
    rows[1:, 1:4] += rng.uniform(-SIZE_JITTER, SIZE_JITTER, size=(extra, 3))
    rows[1:, 4:7] = np.where(rng.random((extra, 3)) < SUBTYPE_MINORITY, -0.5, 0.5)
    return rows


@dataclass
class AuctionRandom:
    """An auction's generators: numpy for the rows and price raises; torch ``decisive`` for
    row 0's augmentation noise; torch ``rows`` for rows 1.. (fine-tuning rounds draw from
    per-patron generators instead, see ``round_seeds``)."""

    numpy: np.random.Generator
    decisive: torch.Generator
    rows: torch.Generator

    @classmethod
    def from_seed(cls, seed: int) -> AuctionRandom:
        numpy_seq, decisive_seq, rows_seq = np.random.SeedSequence(seed).spawn(3)

        def torch_generator(seq: np.random.SeedSequence) -> torch.Generator:
            return torch.Generator().manual_seed(int(seq.generate_state(1, np.uint64)[0]))

        return cls(
            np.random.default_rng(numpy_seq),
            torch_generator(decisive_seq),
            torch_generator(rows_seq),
        )

    def state(self) -> dict[str, Any]:
        return {
            "numpy": self.numpy.bit_generator.state,
            "decisive": self.decisive.get_state(),
            "rows": self.rows.get_state(),
        }

    def load(self, state: dict[str, Any]) -> None:
        self.numpy.bit_generator.state = state["numpy"]
        self.decisive.set_state(state["decisive"])
        self.rows.set_state(state["rows"])


def scores_all_rows(config: MarketConfig, iteration: int) -> bool:
    """Whether rows 1.. are scored in this iteration."""
    return config.evaluate_all_rows or (config.fine_tune and iteration < config.fine_tune_rounds)


def fine_tunes_after(config: MarketConfig, iteration: int) -> bool:
    """Whether patrons fine-tune after this iteration (if the auction goes on)."""
    return config.fine_tune and iteration < config.fine_tune_rounds


def round_seeds(seed: int, iteration: int) -> tuple[int, int]:
    """(fine_tune_seed, augmentation_seed) of the fine-tuning round after ``iteration`` of the
    auction seeded ``seed``."""
    base = derive_seeds(seed, iteration)
    shuffle, noise = derive_seeds(base, [FINE_TUNE_STREAM, AUGMENTATION_STREAM]).tolist()
    return int(shuffle), int(noise)


@dataclass(frozen=True)
class FineTuneRound:
    """A fine-tuning round awaiting the patrons' results (remote mode)."""

    iteration: int
    """The iteration it follows."""
    rows: np.ndarray
    """(R, 8) float64: the item rows after that iteration (new price and buy fractions)."""
    fine_tune_seed: int
    augmentation_seed: int
    patrons: list[int]
    """Positions of the patrons asked (the active ones)."""


FROZEN_IN_ROUNDS = "only weights and biases change in a fine-tuning round"


def round_update_problems(current: Manifest, update: Manifest) -> list[tuple[str, str]]:
    """What ``update`` changes beyond the weights and biases of ``current``, as (dotted path,
    message) pairs: a fine-tuning round moves the numbers, never the model's design
    (activations, augmentation, settings, names)."""
    return design_changes(current.model_dump(mode="json"), update.model_dump(mode="json"))


def design_changes(current: dict[str, Any], update: dict[str, Any]) -> list[tuple[str, str]]:
    """``round_update_problems`` on the manifests' JSON forms."""
    problems: list[tuple[str, str]] = []

    def walk(before: Any, after: Any, path: tuple[str, ...]) -> None:
        if path[-1:] == ("bias",) or path[-2:-1] == ("weights",):
            return
        if isinstance(before, dict) and isinstance(after, dict) and before.keys() == after.keys():
            for key in before:
                walk(before[key], after[key], (*path, key))
        elif before != after:
            problems.append((".".join(path), f"{FROZEN_IN_ROUNDS}: must stay {before!r}"))

    walk(current, update, ())
    return problems


def _runs(work: list[int], limit: int) -> list[tuple[int, int]]:
    """(first, last) of consecutive runs of items whose ``work`` adds up to at most ``limit``
    (a run holds at least one item)."""
    runs, first, total = [], 0, 0
    for i, w in enumerate(work):
        if i > first and total + w > limit:
            runs.append((first, i))
            first, total = i, 0
        total += w
    runs.append((first, len(work)))
    return runs


class MarketBatch:
    """Independent auctions advanced in lock-step, all patrons in one tensor batch.

    ``auctions`` is a sequence of (manifests, config); all configs need the same ``n_rows``.
    Patron indices in records are positions in the auction's own manifest list.
    """

    def __init__(
        self,
        auctions: Sequence[tuple[Sequence[Manifest], MarketConfig]],
        *,
        rescreen: Sequence[Rescreen | None] | None = None,
        rescreen_batch: RescreenBatch | None = None,
        dtype: torch.dtype = torch.float64,
        patrons: FSNBatch | None = None,
    ) -> None:
        """``patrons``, if given, is ``from_manifests`` of every auction's manifests in order,
        built by the caller (who may stack it from parts it already holds)."""
        if not auctions:
            raise ValueError("no auction")
        self.configs = [config for _, config in auctions]
        if len({c.n_rows for c in self.configs}) != 1:
            raise ValueError("auctions run in one batch need the same n_rows")
        self.n_rows = self.configs[0].n_rows
        self.rescreen = list(rescreen) if rescreen is not None else [None] * len(auctions)
        self.rescreen_batch = rescreen_batch
        sizes = [len(manifests) for manifests, _ in auctions]
        if min(sizes) < 1:
            raise ValueError("every auction needs at least one patron")
        A = len(auctions)
        self.owner = np.repeat(np.arange(A), sizes)
        self.first = np.concatenate(([0], np.cumsum(sizes)))
        self.local = np.arange(len(self.owner)) - self.first[self.owner]
        if patrons is not None and patrons.n_patrons != sum(sizes):
            raise ValueError("patrons must hold every auction's manifests")
        self.batch = (
            patrons
            if patrons is not None
            else from_manifests([m for manifests, _ in auctions for m in manifests], dtype)
        )
        self.accepted = (
            {k: v.clone() for k, v in self.batch.parameters().items()}
            if rescreen_batch is not None or any(cb is not None for cb in self.rescreen)
            else None
        )
        self.scale = noise_scale(self.batch)
        self.copies = self.batch.copies.numpy()
        self.random = [AuctionRandom.from_seed(c.seed) for c in self.configs]
        rows = np.stack(
            [item_rows(c, r.numpy) for c, r in zip(self.configs, self.random, strict=True)]
        )
        self.rows = torch.tensor(rows, dtype=dtype)
        self.price = np.array([c.base_price for c in self.configs], dtype=np.float64)
        self.threshold = np.array([c.threshold_sell_price for c in self.configs], dtype=np.float64)
        self.decrement = np.array([c.decrement for c in self.configs], dtype=np.float64)
        self.n_available = np.array([c.n_fish for c in self.configs], dtype=np.int64)
        self.iteration = np.zeros(A, dtype=np.int64)
        self.finished = np.zeros(A, dtype=bool)
        self.stop_reason: list[str | None] = [None] * A
        self.active = np.ones(len(self.owner), dtype=bool)
        self.pending = np.zeros(A, dtype=bool)
        """Auctions whose remote fine-tuning round awaits ``apply_round``."""
        self._voters: tuple[bytes, FSNBatch] | None = None

    @property
    def n_auctions(self) -> int:
        return len(self.configs)

    # --- one iteration ------------------------------------------------------------------------

    def step(self) -> list[IterationRecord | None]:
        """Advance every unfinished auction by one iteration (None for finished ones)."""
        running = ~self.finished
        if not running.any():
            raise RuntimeError("every auction has finished")
        if self.pending.any():
            waiting = np.flatnonzero(self.pending).tolist()
            raise RuntimeError(f"auctions {waiting} await their fine-tuning round (apply_round)")
        A = self.n_auctions
        iteration = self.iteration.copy()
        iterations = iteration.tolist()
        playing = np.flatnonzero(running).tolist()
        full = np.zeros(A, dtype=bool)
        full[[a for a in playing if scores_all_rows(self.configs[a], iterations[a])]] = True
        # 1. Evaluate: every active patron votes on the rows; only row 0 decides.
        voters = np.flatnonzero(self.active & running[self.owner])
        owner = self.owner[voters]
        groups = self._groups(voters)
        decisions = self._evaluate(voters, groups, full)
        row0 = decisions[:, 0]
        votes = np.bincount(owner * 3 + row0, minlength=3 * A).reshape(A, 3)
        scored = full[owner][:, None] | (np.arange(decisions.shape[1]) == 0)[None, :]
        row_votes = np.bincount(
            ((owner[:, None] * 3) + decisions)[scored], minlength=3 * A
        ).reshape(A, 3)
        voting = [a for a, _, _ in groups]
        starts = np.array([start for _, start, _ in groups])
        sizes = np.array([stop - start for _, start, stop in groups])
        buy_fraction = np.zeros((A, decisions.shape[1]))
        buys = np.add.reduceat((decisions == 0).astype(np.float64), starts, axis=0)
        buy_fraction[voting] = buys / sizes[:, None]

        # 2. Price rules: high demand raises the price (and the stalemate threshold); low
        #    demand sells to every row-0 buyer at the current price and lowers it.
        start_price, start_available = self.price.copy(), self.n_available.copy()
        n_buy = votes[:, 0]
        high = running & (n_buy > self.n_available)
        low = running & ~high
        new_price = np.where(low, start_price - self.decrement, start_price)
        for a in np.flatnonzero(high).tolist():
            cfg = self.configs[a]
            new_price[a] = (
                start_price[a] + cfg.increment - self.random[a].numpy.uniform(0, 4) * cfg.decrement
            )
        self.threshold = np.where(high, start_price + self.decrement, self.threshold)
        self.price = new_price
        bought = voters[(row0 == 0) & low[owner]]
        quitted = voters[row0 == 2]
        self.n_available = self.n_available - np.where(low, n_buy, 0)
        self.active[bought] = False
        self.active[quitted] = False

        # 3. The rows see the new price and this round's buy fractions.
        self.rows[:, :, PRICE] = torch.tensor(self.price, dtype=self.rows.dtype)[:, None]
        fractions = torch.tensor(buy_fraction, dtype=self.rows.dtype)
        wide = torch.from_numpy(np.flatnonzero(full))
        narrow = torch.from_numpy(np.flatnonzero(running & ~full))
        self.rows[wide, :, BUY_FRACTION] = fractions[wide]
        self.rows[narrow, 0, BUY_FRACTION] = fractions[narrow, 0]

        # 4. Stop conditions, then fine-tuning in the first rounds.
        left = np.bincount(self.owner[self.active], minlength=A).tolist()
        available, price, threshold = (
            self.n_available.tolist(),
            self.price.tolist(),
            self.threshold.tolist(),
        )
        reasons: list[str | None] = [None] * A
        for a in playing:
            if available[a] == 0:
                reasons[a] = "sold_out"
            elif left[a] == 0:
                reasons[a] = "no_patrons"
            elif price[a] < threshold[a]:
                reasons[a] = "stalemate"
            elif iterations[a] + 1 >= self.configs[a].max_iterations:
                reasons[a] = "max_iterations"
        self.iteration[running] += 1
        for a in playing:
            if reasons[a] is not None:
                self.finished[a] = True
                self.stop_reason[a] = reasons[a]
        tune = np.zeros(A, dtype=bool)
        tune[
            [
                a
                for a in playing
                if reasons[a] is None and fine_tunes_after(self.configs[a], iterations[a])
            ]
        ] = True
        remote = np.array([c.fine_tune_mode == "remote" for c in self.configs])
        self.pending = tune & remote
        kept, reverted = self._fine_tune(tune & ~remote, iteration)

        records: list[IterationRecord | None] = [None] * A
        buyers, quitters = self._by_auction(bought), self._by_auction(quitted)
        start_prices, start_availables = start_price.tolist(), start_available.tolist()
        vote_counts, row_vote_counts = votes.tolist(), row_votes.tolist()
        for a in playing:
            records[a] = IterationRecord(
                iteration=iterations[a],
                price=start_prices[a],
                n_available=start_availables[a],
                votes=dict(zip(ACTIONS, vote_counts[a], strict=True)),
                row_votes=dict(zip(ACTIONS, row_vote_counts[a], strict=True)),
                buyers=[(i, start_prices[a]) for i in buyers[a]],
                quitters=quitters[a],
                next_price=price[a],
                n_available_after=available[a],
                finished=reasons[a] is not None,
                stop_reason=reasons[a],
                fine_tuned=kept.get(a, []),
                reverted=reverted.get(a, []),
            )
        return records

    def _by_auction(self, patrons: np.ndarray) -> list[list[int]]:
        """The local indices of ``patrons`` (sorted), one list per auction."""
        local = self.local[patrons].tolist()
        cuts = np.searchsorted(self.owner[patrons], np.arange(self.n_auctions + 1)).tolist()
        return [local[cuts[a] : cuts[a + 1]] for a in range(self.n_auctions)]

    def _groups(self, patrons: np.ndarray) -> list[tuple[int, int, int]]:
        """(auction, start, stop) of the runs of ``patrons`` (sorted) that share an auction."""
        owner = self.owner[patrons]
        cuts = np.flatnonzero(np.diff(owner)) + 1
        starts = np.concatenate(([0], cuts))
        stops = np.concatenate((cuts, [len(patrons)]))
        return list(zip(owner[starts].tolist(), starts.tolist(), stops.tolist(), strict=True))

    def _evaluate(
        self, voters: np.ndarray, groups: list[tuple[int, int, int]], full: np.ndarray
    ) -> np.ndarray:
        """Decisions (n_voters, R_scored) of the voters; each auction draws its own noise.
        Auctions are evaluated a few at a time, so that the tensors stay in the cache."""
        width = self.n_rows if full.any() else 1
        voting = self._voting(voters)
        copies = self.copies[voters]
        starts = np.array([start for _, start, _ in groups])
        own_copies = np.maximum.reduceat(copies, starts).tolist()  # each auction's largest D
        work = np.add.reduceat(copies, starts) * width
        decisions = []
        for first, last in _runs(work.tolist(), EVALUATION_CHUNK):
            chunk = groups[first:last]
            start, stop = chunk[0][1], chunk[-1][2]
            n_copies = max(own_copies[first:last])
            copies_of = own_copies[first:last]
            normal = self._normals(chunk, copies_of, 1, lambda r: r.decisive)
            if width > 1:
                rest = self._normals(chunk, copies_of, width - 1, lambda r: r.rows, full)
                normal = torch.cat((normal, rest), dim=1)
            mine = voters[start:stop]
            noise = normal * self.scale[torch.from_numpy(mine), None, :n_copies]  # float64
            x = self.rows[torch.from_numpy(self.owner[mine]), :width]
            decisions.append(decide(voting.select(slice(start, stop)), x, noise))
        return torch.cat(decisions).numpy()

    def _normals(
        self,
        chunk: list[tuple[int, int, int]],
        copies: list[int],
        n_rows: int,
        stream: Callable[[AuctionRandom], torch.Generator],
        drawn: np.ndarray | None = None,
    ) -> Tensor:
        """N(0, 1) draws (voters of ``chunk``, n_rows, D, 8): each auction draws its voters ×
        n_rows × its own D (``copies``) from its ``stream`` generator in one go; zeros on
        padded copies and for the auctions that ``drawn`` (bool per auction) leaves out."""
        start, stop = chunk[0][1], chunk[-1][2]
        n_copies = max(copies)
        draws = [drawn is None or bool(drawn[a]) for a, _, _ in chunk]
        whole = all(draws) and min(copies) == n_copies
        shape = (stop - start, n_rows, n_copies, len(INPUTS))
        normal = (torch.empty if whole else torch.zeros)(shape, dtype=torch.float32)
        for (a, lo, hi), c, draw in zip(chunk, copies, draws, strict=True):
            if not draw:
                continue
            into = normal[lo - start : hi - start]
            generator = stream(self.random[a])
            if c == n_copies:
                standard_normal((hi - lo, n_rows, c), generator, out=into)
            else:
                into[:, :, :c] = standard_normal((hi - lo, n_rows, c), generator)
        return normal

    def _voting(self, voters: np.ndarray) -> FSNBatch:
        """The sub-batch of the voters (kept while neither they nor the parameters change)."""
        if len(voters) == self.batch.n_patrons:
            return self.batch
        key = voters.tobytes()
        if self._voters is None or self._voters[0] != key:
            self._voters = (key, self.batch.select(voters))
        return self._voters[1]

    def _fine_tune(
        self, tune: np.ndarray, iteration: np.ndarray
    ) -> tuple[dict[int, list[int]], dict[int, list[int]]]:
        """Fine-tune the active patrons of the auctions in ``tune`` after their ``iteration``;
        re-screen if asked."""
        patrons = np.flatnonzero(self.active & tune[self.owner])
        if len(patrons) == 0:
            return {}, {}
        sub = self.batch.select(patrons)
        seeds = np.zeros((self.n_auctions, 2), dtype=np.uint64)
        for a in np.flatnonzero(tune).tolist():
            seeds[a] = round_seeds(self.configs[a].seed, int(iteration[a]))
        owner = self.owner[patrons]
        tuned = fine_tune_round(
            sub,
            self.rows,
            seeds[owner, 0],
            seeds[owner, 1],
            self.local[patrons],
            dataset=torch.from_numpy(owner),
        )
        self._voters = None
        index = torch.from_numpy(patrons)
        for name, value in tuned.parameters().items():
            getattr(self.batch, name)[index] = value
        moved = patrons[sub.epochs.numpy() > 0]
        kept: dict[int, list[int]] = {}
        reverted: dict[int, list[int]] = {}
        judged = (
            np.asarray(self.rescreen_batch(self.batch.select(moved)), dtype=bool).tolist()
            if self.rescreen_batch is not None and len(moved)
            else [None] * len(moved)
        )
        for i, a, local, verdict in zip(
            moved.tolist(),
            self.owner[moved].tolist(),
            self.local[moved].tolist(),
            judged,
            strict=True,
        ):
            check = self.rescreen[a]
            if verdict is not None:
                keep = verdict
            else:
                keep = check is None or check(local, to_manifest(self.batch, i))
            if keep:
                kept.setdefault(a, []).append(local)
                if self.accepted is not None:
                    for name, value in self.batch.parameters().items():
                        self.accepted[name][i] = value[i]
            else:
                reverted.setdefault(a, []).append(local)
                assert self.accepted is not None
                for name, value in self.batch.parameters().items():
                    value[i] = self.accepted[name][i]
        return kept, reverted

    # --- remote fine-tuning rounds -----------------------------------------------------------

    def pending_round(self, auction: int) -> FineTuneRound | None:
        """The auction's fine-tuning round awaiting ``apply_round``, if any."""
        if not self.pending[auction]:
            return None
        iteration = int(self.iteration[auction]) - 1
        fine_tune_seed, augmentation_seed = round_seeds(self.configs[auction].seed, iteration)
        mine = slice(self.first[auction], self.first[auction + 1])
        return FineTuneRound(
            iteration=iteration,
            rows=self.rows[auction].numpy().copy(),
            fine_tune_seed=fine_tune_seed,
            augmentation_seed=augmentation_seed,
            patrons=np.flatnonzero(self.active[mine]).tolist(),
        )

    def apply_round(self, auction: int, updates: Mapping[int, Manifest]) -> None:
        """Close the auction's pending round: patron ``position`` takes the weights and biases
        of ``updates[position]``; the others keep theirs. Raises ValueError (nothing applied)
        for a patron not asked in the round or an update that changes more than the numbers."""
        pending = self.pending_round(auction)
        if pending is None:
            raise ValueError(f"auction {auction} has no pending fine-tuning round")
        index = []
        for position, manifest in updates.items():
            if position not in pending.patrons:
                raise ValueError(f"patron {position} is not asked in this round")
            i = int(self.first[auction]) + position
            problems = round_update_problems(to_manifest(self.batch, i), manifest)
            if problems:
                raise ValueError(f"patron {position}: {problems[0][0]}: {problems[0][1]}")
            index.append(i)
        if index:
            new = from_manifests([updates[p] for p in updates], self.batch.dtype).parameters()
            at = torch.tensor(index)
            for name, value in self.batch.parameters().items():
                value[at] = new[name]
            self._voters = None
        self.pending[auction] = False

    # --- state --------------------------------------------------------------------------------

    def manifests(self, auction: int) -> list[Manifest]:
        """The auction's patrons with their current (possibly fine-tuned) parameters."""
        return [
            to_manifest(self.batch, i) for i in range(self.first[auction], self.first[auction + 1])
        ]

    def state(self) -> dict[str, Any]:
        """Everything needed to continue (tensors, numbers, generator states)."""
        return {
            "format": CHECKPOINT_FORMAT,
            "participants": list(self.batch.participants),
            "price": self.price.tolist(),
            "threshold": self.threshold.tolist(),
            "n_available": self.n_available.tolist(),
            "iteration": self.iteration.tolist(),
            "finished": self.finished.tolist(),
            "stop_reason": list(self.stop_reason),
            "active": torch.from_numpy(self.active.copy()),
            "rows": self.rows.clone(),
            # parameters move only by fine-tuning; otherwise they are the manifests' own
            "parameters": {k: v.clone() for k, v in self.batch.parameters().items()}
            if any(c.fine_tune for c in self.configs)
            else None,
            "accepted": None
            if self.accepted is None
            else {k: v.clone() for k, v in self.accepted.items()},
            "random": [r.state() for r in self.random],
            "pending": self.pending.tolist(),
        }

    def load_state(self, state: dict[str, Any]) -> None:
        """Continue from ``state()`` of a batch built from the same manifests and configs."""
        if (
            state.get("format") not in (1, CHECKPOINT_FORMAT)
            or state["participants"] != self.batch.participants
        ):
            raise ValueError("checkpoint does not belong to these manifests")
        self.price = np.array(state["price"], dtype=np.float64)
        self.threshold = np.array(state["threshold"], dtype=np.float64)
        self.n_available = np.array(state["n_available"], dtype=np.int64)
        self.iteration = np.array(state["iteration"], dtype=np.int64)
        self.finished = np.array(state["finished"], dtype=bool)
        self.stop_reason = list(state["stop_reason"])
        self.active = state["active"].numpy().copy()
        self.rows = state["rows"].to(self.rows.dtype).clone()
        if state["parameters"] is not None:
            self.batch = self.batch.with_parameters(
                {k: v.clone() for k, v in state["parameters"].items()}
            )
        self._voters = None
        if state["accepted"] is not None:
            self.accepted = {k: v.clone() for k, v in state["accepted"].items()}
        for random, saved in zip(self.random, state["random"], strict=True):
            random.load(saved)
        self.pending = np.array(state.get("pending", [False] * self.n_auctions), dtype=bool)


class Market:
    """One auction (see the module docstring); ``rescreen`` re-checks fine-tuned patrons."""

    def __init__(
        self,
        manifests: Sequence[Manifest],
        config: MarketConfig,
        *,
        rescreen: Rescreen | None = None,
        rescreen_batch: RescreenBatch | None = None,
    ) -> None:
        self.config = config
        self._engine = MarketBatch(
            [(manifests, config)], rescreen=[rescreen], rescreen_batch=rescreen_batch
        )

    @property
    def finished(self) -> bool:
        return bool(self._engine.finished[0])

    @property
    def iteration(self) -> int:
        """Iterations done so far."""
        return int(self._engine.iteration[0])

    @property
    def price(self) -> float:
        return float(self._engine.price[0])

    @property
    def n_available(self) -> int:
        return int(self._engine.n_available[0])

    @property
    def stop_reason(self) -> str | None:
        return self._engine.stop_reason[0]

    def step(self) -> IterationRecord:
        """One iteration; raises RuntimeError once the auction has finished."""
        if self.finished:
            raise RuntimeError("the auction has finished")
        record = self._engine.step()[0]
        assert record is not None
        return record

    def run(self) -> Iterator[IterationRecord]:
        """Iterate to the end, yielding each iteration's record."""
        while not self.finished:
            yield self.step()

    def checkpoint(self) -> bytes:
        """The state after the last iteration, as bytes (``restore`` continues from it)."""
        buffer = io.BytesIO()
        torch.save(self._engine.state(), buffer)
        return buffer.getvalue()

    @classmethod
    def restore(
        cls,
        manifests: Sequence[Manifest],
        config: MarketConfig,
        blob: bytes,
        *,
        rescreen: Rescreen | None = None,
        rescreen_batch: RescreenBatch | None = None,
    ) -> Market:
        """The auction of ``manifests`` and ``config`` as it was at ``checkpoint()``."""
        market = cls(manifests, config, rescreen=rescreen, rescreen_batch=rescreen_batch)
        state = torch.load(io.BytesIO(blob), weights_only=True)
        market._engine.load_state(state)
        return market

    def current_manifests(self) -> list[Manifest]:
        """The patrons with their current (possibly fine-tuned) parameters."""
        return self._engine.manifests(0)

    @property
    def pending_round(self) -> FineTuneRound | None:
        """The remote fine-tuning round awaiting ``apply_round`` (``step`` refuses until then)."""
        return self._engine.pending_round(0)

    def apply_round(self, updates: Mapping[int, Manifest]) -> None:
        """Close the pending round with the patrons' fine-tuned manifests by position (see
        ``MarketBatch.apply_round``)."""
        self._engine.apply_round(0, updates)


def run_auction(manifests: Sequence[Manifest], config: MarketConfig) -> list[IterationRecord]:
    """Run one auction to the end; its records."""
    return list(Market(manifests, config).run())
