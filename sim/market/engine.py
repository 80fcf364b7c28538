"""``MarketBatch``: independent auctions advanced in lock-step, every patron of every auction
in one tensor batch (the iteration itself is specified in ``sim.market``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from agents.batch import FSNBatch, from_manifests, to_manifest
from agents.fine_tuning import fine_tune_round
from agents.forward import ACTIONS, activations, decide, noise_scale, standard_normal
from agents.manifest import INPUTS, Manifest
from sim.market import rounds
from sim.market.config import MarketConfig, fine_tunes_after, scores_all_rows
from sim.market.design import Design, design
from sim.market.items import BUY_FRACTION, PRICE, item_rows
from sim.market.randomness import AuctionRandom, round_seeds
from sim.market.records import IterationRecord, VoteExplanation
from sim.market.rounds import FineTuneRound

Rescreen = Callable[[int, Manifest], bool]
"""Called as ``rescreen(patron_index, fine_tuned_manifest)``; False reverts that patron."""
Refusal = list[dict[str, str]]
"""Why a re-screening reverted a patron: the screener's reasons, each ``{rule, neuron,
message}`` (empty when the judge gave none)."""
RescreenBatch = Callable[[FSNBatch], "np.ndarray | Sequence[bool | Refusal]"]
"""Called once per fine-tuning round with every fine-tuned patron of the batch's auctions (a
sub-batch, in batch order); returns one judgement per patron: True keeps it; False, or the
``Refusal`` of its reasons, reverts it."""

EXPLAINED = (
    ("sensor", ("PG", "SZ", "LSR", "ST")),
    ("decision", ("B", "L", "Q")),
    ("judgement", ("PGL", "BC", "FQ")),
    ("pfc", ("T", "F")),
)
"""The neurons of a vote's explanation, by the part of the network they belong to."""
EXPLAINED_NEURONS = [name for _, names in EXPLAINED for name in names]

PRICE_DECIMALS = 5
"""Prices are recorded (an iteration's price, a purchase's) rounded to this many decimals, as
the reference's records are; the market itself moves on the unrounded price."""


def recorded(prices: list[float]) -> list[float]:
    """Prices as records keep them (``PRICE_DECIMALS``): 4.8, not 4.800000000000004."""
    return [round(price, PRICE_DECIMALS) for price in prices]


EVALUATION_CHUNK = 32_000
"""(patron, row, copy) evaluations per ``decide`` call: bigger tensors fall out of the cache and
each evaluation gets slower."""


@contextmanager
def single_thread() -> Iterator[None]:
    """Run torch on one thread inside the block: the auction's tensors are small, and
    intra-op threads only add contention."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


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


def _judgement(judged: object) -> bool | Refusal:
    """One of ``RescreenBatch``'s judgements: a bool (numpy's too), or a refusal's reasons."""
    if isinstance(judged, bool | np.bool_):
        return bool(judged)
    if not isinstance(judged, Sequence):
        raise TypeError(f"a re-screening judgement is a bool or a list of reasons: {judged!r}")
    return [dict(reason) for reason in judged]


class _Votes(NamedTuple):
    """One iteration's votes."""

    voters: np.ndarray
    """The patrons who voted (batch positions, sorted)."""
    owner: np.ndarray
    """Their auctions."""
    row0: np.ndarray
    """Their row-0 decisions (indices into ``ACTIONS``)."""
    counts: np.ndarray
    """(A, 3): each auction's row-0 buy / hold / quit votes."""
    row_counts: np.ndarray
    """(A, 3): the same over every scored row."""
    buy_fraction: np.ndarray
    """(A, scored rows): each row's f, the buy votes over the voters its auction's
    ``buy_fraction`` rule counts."""
    explained: np.ndarray | None
    """(voters, len(EXPLAINED_NEURONS)): their neurons on row 0, when the batch explains."""
    row: np.ndarray | None
    """(A, 8): each auction's row 0 as voted on, when the batch explains."""


class _Moves(NamedTuple):
    """What the price rules did in one iteration."""

    price: np.ndarray
    """Each auction's price at the start of the iteration."""
    n_available: np.ndarray
    """Its fish available at the start of the iteration."""
    bought: np.ndarray
    """The patrons who bought (batch positions, sorted)."""
    quitted: np.ndarray
    """The patrons who quit."""


def _starts(configs: Sequence[MarketConfig]) -> tuple[list[AuctionRandom], np.ndarray]:
    """Each auction's generators and item rows as it starts (its rows drawn). Auctions that
    share a seed and the rows' settings start alike, so their start is made once and copied
    (a batch of test auctions repeats a few seeds many times)."""
    made: dict[tuple[int, int, float], int] = {}
    randoms: list[AuctionRandom] = []
    rows: list[np.ndarray] = []
    for config in configs:
        first = made.setdefault((config.seed, config.n_rows, config.base_price), len(randoms))
        if first < len(randoms):
            randoms.append(randoms[first].copy())
            rows.append(rows[first])
            continue
        random = AuctionRandom.from_seed(config.seed)
        rows.append(item_rows(config, random.numpy))
        randoms.append(random)
    return randoms, np.stack(rows)


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
        explain: bool = False,
    ) -> None:
        """``patrons``, if given, is ``from_manifests`` of every auction's manifests in order,
        built by the caller (who may stack it from parts it already holds). ``explain`` adds
        each voter's neurons to the records (one more row-0 pass per iteration; the votes are
        the same)."""
        if not auctions:
            raise ValueError("no auction")
        self.configs = [config for _, config in auctions]
        if len({c.n_rows for c in self.configs}) != 1:
            raise ValueError("auctions run in one batch need the same n_rows")
        self.n_rows = self.configs[0].n_rows
        self.rescreen = list(rescreen) if rescreen is not None else [None] * len(auctions)
        self.rescreen_batch = rescreen_batch
        self.explain = explain
        sizes = [len(manifests) for manifests, _ in auctions]
        if min(sizes) < 1:
            raise ValueError("every auction needs at least one patron")
        A = len(auctions)
        self.owner = np.repeat(np.arange(A), sizes)
        self.first = np.concatenate(([0], np.cumsum(sizes)))
        self.local = np.arange(len(self.owner)) - self.first[self.owner]
        if patrons is not None and patrons.n_patrons != sum(sizes):
            raise ValueError("patrons must hold every auction's manifests")
        self._given = [manifests for manifests, _ in auctions]
        self._designs: dict[tuple[int, int], Design] = {}
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
        self.random, rows = _starts(self.configs)
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
        return self._records(*self._advance())

    def step_sales(self) -> list[list[tuple[int, float]]]:
        """Advance like ``step``, telling only each auction's purchases of the iteration
        (``IterationRecord.buyers``: local index, price; empty for finished auctions), without
        building the records (many small objects a step, for lock-step batches of many short
        auctions such as the screener's test auctions)."""
        moves = self._advance()[3]
        sales: list[list[tuple[int, float]]] = [[] for _ in range(self.n_auctions)]
        if len(moves.bought):
            prices = recorded(moves.price.tolist())
            for a, local in zip(
                self.owner[moves.bought].tolist(), self.local[moves.bought].tolist(), strict=True
            ):
                sales[a].append((local, prices[a]))
        return sales

    def _advance(
        self,
    ) -> tuple[
        list[int],
        list[int],
        _Votes,
        _Moves,
        list[str | None],
        dict[int, list[int]],
        dict[int, list[tuple[int, Refusal]]],
    ]:
        """One iteration of every unfinished auction: what ``_records`` reports of it."""
        running = ~self.finished
        if not running.any():
            raise RuntimeError("every auction has finished")
        if self.pending.any():
            waiting = np.flatnonzero(self.pending).tolist()
            raise RuntimeError(f"auctions {waiting} await their fine-tuning round (apply_round)")
        iteration = self.iteration.copy()
        iterations = iteration.tolist()
        playing = np.flatnonzero(running).tolist()
        full = np.zeros(self.n_auctions, dtype=bool)
        full[[a for a in playing if scores_all_rows(self.configs[a], iterations[a])]] = True
        votes = self._vote(running, full)
        moves = self._apply_price_rules(running, votes)
        self._update_rows(running, full, votes.buy_fraction)
        reasons = self._stop(playing, iterations)
        self.iteration[running] += 1
        for a in playing:
            if reasons[a] is not None:
                self.finished[a] = True
                self.stop_reason[a] = reasons[a]
        tune = np.zeros(self.n_auctions, dtype=bool)
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
        return playing, iterations, votes, moves, reasons, kept, reverted

    def _vote(self, running: np.ndarray, full: np.ndarray) -> _Votes:
        """1. Every active patron of the running auctions votes on the rows (all of them where
        ``full``, else row 0); only row 0 decides."""
        A = self.n_auctions
        voters = np.flatnonzero(self.active & running[self.owner])
        owner = self.owner[voters]
        groups = self._groups(voters)
        row = self.rows[:, 0].numpy().copy() if self.explain else None
        decisions, explained = self._evaluate(voters, groups, full)
        row0 = decisions[:, 0]
        counts = np.bincount(owner * 3 + row0, minlength=3 * A).reshape(A, 3)
        scored = full[owner][:, None] | (np.arange(decisions.shape[1]) == 0)[None, :]
        row_counts = np.bincount(
            ((owner[:, None] * 3) + decisions)[scored], minlength=3 * A
        ).reshape(A, 3)
        voting = [a for a, _, _ in groups]
        starts = np.array([start for _, start, _ in groups])
        sizes = np.array([stop - start for _, start, stop in groups])
        buy_fraction = np.zeros((A, decisions.shape[1]))
        buys = np.add.reduceat((decisions == 0).astype(np.float64), starts, axis=0)
        holds = np.add.reduceat((decisions == 1).astype(np.float64), starts, axis=0)
        staying = np.array([self.configs[a].buy_fraction == "staying" for a in voting])
        counted = np.where(staying[:, None], buys + holds, sizes[:, None])
        buy_fraction[voting] = buys / np.maximum(counted, 1)
        return _Votes(voters, owner, row0, counts, row_counts, buy_fraction, explained, row)

    def _apply_price_rules(self, running: np.ndarray, votes: _Votes) -> _Moves:
        """2. High demand raises the price (and the stalemate threshold); low demand sells to
        every row-0 buyer at the current price and lowers it. Buyers and quitters leave."""
        start_price, start_available = self.price.copy(), self.n_available.copy()
        n_buy = votes.counts[:, 0]
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
        bought = votes.voters[(votes.row0 == 0) & low[votes.owner]]
        quitted = votes.voters[votes.row0 == 2]
        self.n_available = self.n_available - np.where(low, n_buy, 0)
        self.active[bought] = False
        self.active[quitted] = False
        return _Moves(start_price, start_available, bought, quitted)

    def _update_rows(self, running: np.ndarray, full: np.ndarray, buy_fraction: np.ndarray) -> None:
        """3. The rows see the new price and this round's buy fractions (row 0 only where the
        other rows were not scored)."""
        self.rows[:, :, PRICE] = torch.tensor(self.price, dtype=self.rows.dtype)[:, None]
        fractions = torch.tensor(buy_fraction, dtype=self.rows.dtype)
        wide = torch.from_numpy(np.flatnonzero(full))
        narrow = torch.from_numpy(np.flatnonzero(running & ~full))
        self.rows[wide, :, BUY_FRACTION] = fractions[wide]
        self.rows[narrow, 0, BUY_FRACTION] = fractions[narrow, 0]

    def _stop(self, playing: list[int], iterations: list[int]) -> list[str | None]:
        """4. Why each auction played this iteration stops now (None: it goes on)."""
        left = np.bincount(self.owner[self.active], minlength=self.n_auctions).tolist()
        available, price, threshold = (
            self.n_available.tolist(),
            self.price.tolist(),
            self.threshold.tolist(),
        )
        reasons: list[str | None] = [None] * self.n_auctions
        for a in playing:
            if available[a] == 0:
                reasons[a] = "sold_out"
            elif left[a] == 0:
                reasons[a] = "no_patrons"
            elif price[a] < threshold[a]:
                reasons[a] = "stalemate"
            elif iterations[a] + 1 >= self.configs[a].max_iterations:
                reasons[a] = "max_iterations"
        return reasons

    def _records(
        self,
        playing: list[int],
        iterations: list[int],
        votes: _Votes,
        moves: _Moves,
        reasons: list[str | None],
        kept: dict[int, list[int]],
        reverted: dict[int, list[tuple[int, Refusal]]],
    ) -> list[IterationRecord | None]:
        """The iteration's record of each auction played (None for the others)."""
        records: list[IterationRecord | None] = [None] * self.n_auctions
        buyers, quitters = self._by_auction(moves.bought), self._by_auction(moves.quitted)
        start_prices, start_availables = recorded(moves.price.tolist()), moves.n_available.tolist()
        vote_counts, row_vote_counts = votes.counts.tolist(), votes.row_counts.tolist()
        price, available = recorded(self.price.tolist()), self.n_available.tolist()
        explanations = self._explanations(votes)
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
                reverted=[local for local, _ in reverted.get(a, [])],
                refusals=[why for _, why in reverted.get(a, [])],
                row=dict(zip(INPUTS, votes.row[a].tolist(), strict=True))
                if votes.row is not None
                else {},
                explanations=explanations[a],
            )
        return records

    def _explanations(self, votes: _Votes) -> list[list[VoteExplanation]]:
        """Each auction's voters' explanations (empty lists when the batch does not explain)."""
        out: list[list[VoteExplanation]] = [[] for _ in range(self.n_auctions)]
        if votes.explained is None:
            return out
        values = votes.explained.tolist()
        local, owner, row0 = (
            self.local[votes.voters].tolist(),
            votes.owner.tolist(),
            votes.row0.tolist(),
        )
        for i, neurons in enumerate(values):
            named = dict(zip(EXPLAINED_NEURONS, neurons, strict=True))
            parts = {part: {n: named[n] for n in names} for part, names in EXPLAINED}
            out[owner[i]].append(VoteExplanation(local[i], ACTIONS[row0[i]], **parts))
        return out

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
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Decisions (n_voters, R_scored) of the voters, each auction drawing its own noise, and
        when the batch explains, their neurons on row 0 (n_voters, len(EXPLAINED_NEURONS)).
        Auctions are evaluated a few at a time, so that the tensors stay in the cache."""
        width = self.n_rows if full.any() else 1
        voting = self._voting(voters)
        copies = self.copies[voters]
        starts = np.array([start for _, start, _ in groups])
        own_copies = np.maximum.reduceat(copies, starts).tolist()  # each auction's largest D
        work = np.add.reduceat(copies, starts) * width
        decisions, explained = [], []
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
            sub = voting.select(slice(start, stop))
            decisions.append(decide(sub, x, noise))
            if self.explain:  # the same row-0 inputs and noise as the votes
                neurons = activations(sub, x[:, :1], noise[:, :1])
                explained.append(torch.cat([neurons[n] for n in EXPLAINED_NEURONS], dim=1))
        return torch.cat(decisions).numpy(), torch.cat(explained).numpy() if explained else None

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

    # --- fine-tuning --------------------------------------------------------------------------

    def set_parameters(self, index: Tensor, values: Mapping[str, Tensor]) -> None:
        """The patrons at ``index`` (batch positions) take ``values`` (trainable tensors by
        name, one row per patron)."""
        self._voters = None
        for name, value in values.items():
            getattr(self.batch, name)[index] = value

    def _fine_tune(
        self, tune: np.ndarray, iteration: np.ndarray
    ) -> tuple[dict[int, list[int]], dict[int, list[tuple[int, Refusal]]]]:
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
        self.set_parameters(torch.from_numpy(patrons), tuned.parameters())
        return self._rescreen(patrons[sub.epochs.numpy() > 0])

    def _rescreen(
        self, moved: np.ndarray
    ) -> tuple[dict[int, list[int]], dict[int, list[tuple[int, Refusal]]]]:
        """Re-screen the patrons the round ``moved``: keep the versions the re-screening
        accepts, revert the others to their last accepted version. (kept local indices,
        reverted (local index, its ``Refusal``)) per auction."""
        kept: dict[int, list[int]] = {}
        reverted: dict[int, list[tuple[int, Refusal]]] = {}
        judged: list[bool | Refusal | None] = (
            [_judgement(j) for j in self.rescreen_batch(self.batch.select(moved))]
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
            if verdict is None:
                verdict = check is None or bool(check(local, to_manifest(self.batch, i)))
            if verdict is True:
                kept.setdefault(a, []).append(local)
                if self.accepted is not None:
                    for name, value in self.batch.parameters().items():
                        self.accepted[name][i] = value[i]
            else:
                reverted.setdefault(a, []).append((local, [] if verdict is False else verdict))
                assert self.accepted is not None
                for name, value in self.batch.parameters().items():
                    value[i] = self.accepted[name][i]
        return kept, reverted

    # --- remote fine-tuning rounds (``sim.market.rounds``) -----------------------------------

    def pending_round(self, auction: int) -> FineTuneRound | None:
        """The auction's fine-tuning round awaiting ``apply_round``, if any."""
        return rounds.pending_round(self, auction)

    def apply_round(self, auction: int, updates: Mapping[int, Manifest]) -> None:
        """Close the auction's pending round: patron ``position`` takes the weights and biases
        of ``updates[position]``, the others keep theirs (ValueError, nothing applied, for a
        patron not asked in the round or an update that changes more than the numbers)."""
        rounds.apply_round(self, auction, updates)

    # --- state (saved and restored by ``sim.market.checkpoint``) -------------------------------

    def replace_batch(self, batch: FSNBatch) -> None:
        """The same patrons from now on with the parameters of ``batch``."""
        self.batch = batch
        self._voters = None

    def entered(self, auction: int, position: int) -> Manifest:
        """The manifest patron ``position`` of ``auction`` entered with."""
        return self._given[auction][position]

    def design(self, auction: int, position: int) -> Design:
        """The design (``sim.market.design``) of patron ``position`` of ``auction``: that of the
        manifest it entered with, which fine-tuning never changes (computed once)."""
        key = (auction, position)
        if key not in self._designs:
            self._designs[key] = design(self.entered(auction, position))
        return self._designs[key]

    def manifests(self, auction: int) -> list[Manifest]:
        """The auction's patrons with their current (possibly fine-tuned) parameters."""
        return [
            to_manifest(self.batch, i) for i in range(self.first[auction], self.first[auction + 1])
        ]

    def manifest(self, auction: int, position: int) -> Manifest:
        """Patron ``position`` of ``auction`` with its current (possibly fine-tuned)
        parameters."""
        if not 0 <= position < self.first[auction + 1] - self.first[auction]:
            raise IndexError(f"auction {auction} has no patron {position}")
        return to_manifest(self.batch, int(self.first[auction]) + position)
