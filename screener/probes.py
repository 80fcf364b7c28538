"""Behavioural probes: clean forward passes of the manifests over a grid of items.

The grid crosses the probe prices (0.3× to 2.5× the base price), three fish qualities
(l = w = g = 0.8, 1, 1.2), all eight sub-types and five previous buy fractions f; augmentation
noise is off (every copy clean), so the probes see the decision the model means. Manifests
with the same activation kinds share a forward pass (up to ``PASS_SIZE`` of them), and each gets
exactly the scores it would get alone. Checks:

* ``buys-cheap``: far below any plausible price, the base fish of the preferred sub-type is
  bought at every f (a rare buyer refuses it unless the others rush or the fish is huge);
* ``always-holds`` / ``always-quits`` / ``never-buys``: some probed item is bought;
* ``refuses-far-too-expensive`` and ``quits-far-too-expensive``: far above any plausible
  price the base fish is not bought firmly in ordinary demand, and not held at any demand
  (holding there means waiting for the price to drop: the saboteur's way to drag the market
  down);
* ``buy-falls-with-price``: the buy margin B − max(L, Q), clipped to a firm decision either
  way, never swings from refusing to buying as the price rises on any probed item;
* ``buys-far-below-floor`` holds a model for an inspector rather than refuse it
  (``inspected``: bars in ``Evidence`` that ``screener.review`` holds on): the base fish bought
  on the decisive row in ordinary demand only below ``FAR_BELOW_FLOOR_FACTOR`` × the base
  price, far under the lowest price an auction reaches (a bidder that can never buy there).
  The bars at 12.5 that hold a keen buyer read its noisy copies too (``screener.noisy``);
* ``sincere-hold``: on the auction's decisive row (the clean base item (p, 1, 1, 1, ½, ½, ½, f))
  at the prices the auction can reach (from the market's stalemate floor up, ``SCAN``), every
  hold is backed by a lower reachable price at which the model buys the fish, at the same f.
  The paper's hold neuron L means "hold (and lower price)": a hold is a bid for a lower price,
  sincere only if the model would buy at a price the auction can still come down to. A model
  that can only hold or quit at every reachable price sits in the auction pulling the demand
  down, however its neurons are wired.

The same pass tells which models hold anywhere on the reachable decisive row (``holds``): only
their votes can hold the market down, so only they go on to the market-impact test.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import torch

from agents.batch import FSNBatch
from agents.forward import clean_logits
from screener import limits
from screener.findings import Array, Checks, Mask, fmt, fmt_price, fmt_scores
from screener.rules import SUBTYPES
from screener.verdict import Evidence

BUY, HOLD, QUIT = range(3)
ACTION_WORDS = ("buys", "holds", "quits")
PRICES = np.array(limits.PROBE_PRICE_FACTORS) * limits.BASE_PRICE
QUALITIES = np.array(limits.PROBE_QUALITIES)
DEMANDS = np.array(limits.PROBE_DEMANDS)
BASE_QUALITY = int(np.flatnonzero(QUALITIES == 1.0)[0])
PREFERRED = 0
"""Index of the preferred sub-type (½, ½, ½) in ``rules.SUBTYPES``."""
GRID_SHAPE = (len(PRICES), len(QUALITIES), len(SUBTYPES), len(DEMANDS))
PASS_SIZE = 64
"""Patrons per forward pass over the grid (and of the noisy scan). The clean pass runs patron-major
with the rows last (``clean_logits``), each patron's rows one contiguous run, so the time per
patron keeps falling up to a re-screening round of 64 (measured on a quiet machine: 0.20 ms per
patron in passes of 16, 0.17 in one pass of 64, and 0.16 against 0.13 for the noisy scan; under
a load of 4 from other jobs the pass size made no difference). Batches of the screening process
(at most 16) and re-screening rounds are one pass."""


def _grid() -> torch.Tensor:
    """All probe items (p, l, w, g, st1, st2, st3, f), price-major, as a (R, 8) float64 tensor."""
    p, q, s, f = np.meshgrid(PRICES, QUALITIES, np.arange(len(SUBTYPES)), DEMANDS, indexing="ij")
    rows = np.stack(
        [p, q, q, q, *(SUBTYPES[s.astype(int), k] for k in range(3)), f], axis=-1
    ).reshape(-1, 8)
    return torch.from_numpy(rows)


GRID = _grid()
CHEAP = PRICES <= limits.CHEAP_FACTOR * limits.BASE_PRICE + 1e-9
FAR_TOO_EXPENSIVE = PRICES >= limits.FAR_TOO_EXPENSIVE_FACTOR * limits.BASE_PRICE - 1e-9
ORDINARY = DEMANDS <= limits.ORDINARY_DEMAND + 1e-9
BUY_MARGIN = "buy margin"
"""The units of a bar on the buy margin B − max(L, Q) (not price: the review margin does not
apply to it)."""
PROBED_PRICE = "probed price"
"""The units of a bar on the decisive-row scan's prices below the floor, 0.1 apart: a price, but
not one the review margin (a fraction of a cent) applies to."""


def _scan_prices() -> tuple[Array, int]:
    """The decisive-row scan's prices, ascending, and the index of the first reachable one (the
    stalemate floor): prices below the floor in steps of ``SCAN_BELOW_STEP``, then every
    decrement from ``HOLD_REACH_SLACK`` decrements under the floor to ``SCAN_RISES`` increments
    above the base price (all from the market's rules)."""
    market = limits.MARKET
    floor, step = market.threshold_sell_price, market.decrement
    slack = floor - limits.HOLD_REACH_SLACK * step
    lowest = limits.WILLINGNESS_TO_PAY_BAND[0] * market.base_price
    below = np.arange(lowest, slack - 1e-9, limits.SCAN_BELOW_STEP)
    top = market.base_price + limits.SCAN_RISES * market.increment
    fine = slack + step * np.arange(round((top - slack) / step) + 1)
    prices: Array = np.round(np.concatenate((below, fine)), 10).astype(np.float64)
    return prices, int(np.searchsorted(prices, floor - 1e-9))


def _lowest_reachable() -> npt.NDArray[np.intp]:
    """Per scan price, the index of the lowest price that backs a hold there: the lowest price
    the auction can still come down to, less ``HOLD_REACH_SLACK`` decrements. Up to the base
    price the auction can be there before any rise, and then walks down to the stalemate floor.
    Above it, the price got there by a rise of at most one increment, and a rise moves the
    stalemate threshold to the price before it plus one decrement: from p the auction can come
    down to p − (increment − decrement) at best."""
    market, prices = limits.MARKET, SCAN_PRICES
    slack = limits.HOLD_REACH_SLACK * market.decrement
    floor = prices[FLOOR_INDEX]
    risen = prices > market.base_price + 1e-9
    lowest = np.where(risen, prices - (market.increment - market.decrement), floor) - slack
    index: npt.NDArray[np.intp] = np.searchsorted(prices, np.maximum(lowest, floor - slack) - 1e-9)
    return index


SCAN_PRICES, FLOOR_INDEX = _scan_prices()
SCAN_DEMANDS = np.array(limits.SCAN_DEMANDS)
ORDINARY_SCAN = SCAN_DEMANDS <= limits.ORDINARY_DEMAND + 1e-9
LOWEST_TOP_BUY = limits.FAR_BELOW_FLOOR_FACTOR * limits.BASE_PRICE
"""``buys-far-below-floor``'s bar: the lowest price (on the scan) at which a model must buy the
base fish in ordinary demand (4.00)."""
REACHABLE = np.arange(len(SCAN_PRICES)) >= FLOOR_INDEX
LOWEST_REACHABLE = _lowest_reachable()


def _scan() -> torch.Tensor:
    """The decisive row (p, 1, 1, 1, ½, ½, ½, f) at every scan price × scan buy fraction."""
    p, f = np.meshgrid(SCAN_PRICES, SCAN_DEMANDS, indexing="ij")
    rows = np.tile(np.array(limits.BASE_ROW), (p.size, 1))
    rows[:, 0], rows[:, -1] = p.reshape(-1), f.reshape(-1)
    return torch.from_numpy(rows)


SCAN = _scan()
DTYPE = torch.float64
"""The screener's arithmetic (probes, noisy scan, test auctions): float64, the market's. A vote
the market decides by less than float32 resolves is decided as the market decides it: a model
whose B and L tie in float32 at every reachable price but whose L wins in float64 by 6e-9 holds
in every auction (tanh(10) is 1 in float32), and a float32 screener saw it buy."""
ROWS = torch.cat((GRID, SCAN)).to(DTYPE)
"""Every probed row: the grid, then the decisive-row scan (one forward pass)."""


class Probed(NamedTuple):
    """The probes' checks over a batch, which models hold somewhere on the reachable decisive
    row (P,), for each its worst hold's distance down to a purchase and the reach allowed
    there (``hold_gap``; nan for a model that never holds), and each model's bars that hold it
    for an inspector when missed (``inspected``; none for scores that overflow)."""

    checks: Checks
    holds: Mask
    gap: Array
    bar: Array
    inspected: list[list[Evidence]]


def _fish(q: int, s: int) -> str:
    quality = {0: "the poorest fish", BASE_QUALITY: "the base fish"}.get(q, "the best fish")
    subtype = ", ".join("½" if v > 0 else "−½" for v in SUBTYPES[s])
    return f"{quality} (l = w = g = {QUALITIES[q]:g}, sub-type ({subtype}))"


def _scores(logits: Array) -> str:
    return fmt_scores(logits)


def probe(batch: FSNBatch) -> Probed:
    """Every behavioural probe over the batch, a few patrons per forward pass (``passes``)."""
    parts = [(index, _judge(_logits(part))) for index, part in passes(batch)]
    if len(parts) == 1:
        return parts[0][1]
    P, first = batch.n_patrons, parts[0][1].checks
    failed = np.empty((P, len(first.rules)), dtype=np.bool_)
    holds = np.empty(P, dtype=np.bool_)
    gap, bar = np.empty(P), np.empty(P)
    owner = np.empty(P, dtype=np.intp)
    local = np.empty(P, dtype=np.intp)
    inspected: list[list[Evidence]] = [[] for _ in range(P)]
    for n, (index, probed) in enumerate(parts):
        failed[index] = probed.checks.failed
        holds[index] = probed.holds
        gap[index], bar[index] = probed.gap, probed.bar
        owner[index] = n
        local[index] = np.arange(len(index))
        for k, p in enumerate(index.tolist()):
            inspected[p] = probed.inspected[k]

    def message(k: int, p: int) -> str:
        return parts[int(owner[p])][1].checks.message(k, int(local[p]))

    checks = Checks(first.rules, first.neurons, failed, message)
    return Probed(checks, holds, gap, bar, inspected)


def passes(batch: FSNBatch) -> list[tuple[npt.NDArray[np.intp], FSNBatch]]:
    """The patrons (their indices, their sub-batch) of each forward pass: at most PASS_SIZE,
    all with the same activation kinds. ``decision_logits`` computes a batch that mixes kinds
    by another formula; grouping by kind gives every patron exactly the scores it gets when
    screened alone."""
    P = batch.n_patrons
    kinds = batch.es_kind.numpy()
    if (kinds == kinds[:1]).all():
        if P <= PASS_SIZE:
            return [(np.arange(P), batch)]
        groups = [np.arange(P)]
    else:
        inverse = np.unique(kinds, axis=0, return_inverse=True)[1].reshape(-1)
        groups = [np.flatnonzero(inverse == g) for g in range(int(inverse.max()) + 1)]
    return [
        (index, batch.select(index))
        for group in groups
        for index in np.array_split(group, -(-len(group) // PASS_SIZE))
    ]


def _logits(batch: FSNBatch) -> Array:
    """[B, L, Q] of every patron on every probed row (``ROWS``), (P, R, 3)."""
    with torch.no_grad():
        return clean_logits(batch.to(DTYPE), ROWS).numpy()


def _decisions(scores: Array) -> tuple[Array, Mask, Mask]:
    """The buy margin B − max(L, Q) and the buy and hold masks of scores (..., 3). The decision
    is the argmax, ties to the lowest index: B when it is not behind (the difference of two
    finite numbers has the sign of the exact one), else L when it is not behind Q, else Q."""
    hold, quit_ = scores[..., HOLD], scores[..., QUIT]
    lead = scores[..., BUY] - np.maximum(hold, quit_)
    buys = lead >= 0
    return lead, buys, ~buys & (hold >= quit_)


Probe = tuple[str, str, Mask, Callable[[int], str]]
"""One probe over P patrons: its rule, its neuron, which patrons fail it, and why patron p
fails."""


class _OnGrid(NamedTuple):
    """P patrons' decisions on the grid."""

    scores: Array
    """(P, prices, qualities, sub-types, demands, 3): B, L, Q."""
    lead: Array
    """The buy margin B − max(L, Q), (P, prices, qualities, sub-types, demands)."""
    buys: Mask
    holds: Mask

    def at(self, p: int, i: int, q: int, s: int, f: int) -> str:
        """What patron p does at grid price i on quality q, sub-type s and buy fraction f."""
        action = int(np.argmax(self.scores[p, i, q, s, f]))
        return (
            f"at price {fmt_price(PRICES[i])} on {_fish(q, s)} with buy fraction "
            f"{DEMANDS[f]:g} it {ACTION_WORDS[action]} ({_scores(self.scores[p, i, q, s, f])})"
        )


def _first(mask: Mask) -> tuple[int, ...]:
    """The index of the first True of ``mask``."""
    return tuple(int(v) for v in np.argwhere(mask)[0])


def _judge(every: Array) -> Probed:
    """The probes of P patrons from their scores ``every`` (P, R, 3) on ``ROWS``."""
    P = len(every)
    finite_cells = np.isfinite(every)
    if finite_cells.all():
        finite, safe = np.ones(P, dtype=np.bool_), every
    else:
        finite = np.all(finite_cells.reshape(P, -1), axis=1)
        safe = np.where(finite_cells, every, 0.0)
    scores = safe[:, : len(GRID)].reshape(P, *GRID_SHAPE, 3)
    grid = _OnGrid(scores, *_decisions(scores))
    scan = safe[:, len(GRID) :].reshape(P, len(SCAN_PRICES), len(SCAN_DEMANDS), 3)
    sincere, holds, gap, bar = _sincere_hold(scan)
    probes: tuple[Probe, ...] = (
        ("probe-non-finite", "B", ~finite, _non_finite_message),
        _buys_cheap(grid),
        *_buys_something(grid),
        *_far_too_expensive(grid),
        _buy_falls_with_price(grid),
        sincere,
        _knife_edge(safe, grid),
    )
    failed = np.empty((P, len(probes)), dtype=np.bool_)
    for k, (_, _, mask, _) in enumerate(probes):
        failed[:, k] = mask
    failed[:, 1:] &= finite[:, None]  # scores that overflow get one reason: probe-non-finite
    checks = Checks(
        tuple(probe[0] for probe in probes),
        tuple(probe[1] for probe in probes),
        failed,
        lambda k, p: probes[k][3](p),
    )
    return Probed(
        checks,
        holds & finite,
        np.where(finite, gap, np.nan),
        np.where(finite, bar, np.nan),
        _inspected(grid, scan, finite),
    )


def _knife_edge(every: Array, grid: _OnGrid) -> Probe:
    """knife-edge: on every probed item (the grid and the decisive-row scan) the leading
    decision score leads the next by at least ``limits.TIE_MARGIN``."""
    ordered = np.sort(every, axis=-1)
    lead = ordered[..., 2] - ordered[..., 1]  # (P, R)
    edge = lead < limits.TIE_MARGIN

    def message(p: int) -> str:
        r = int(np.flatnonzero(edge[p])[0])
        if r < len(GRID):
            i, q, s, f = np.unravel_index(r, GRID_SHAPE)
            where = grid.at(p, int(i), int(q), int(s), int(f))
        else:
            i, f = np.unravel_index(r - len(GRID), (len(SCAN_PRICES), len(SCAN_DEMANDS)))
            scores = every[p, r]
            action = ACTION_WORDS[int(np.argmax(scores))]
            where = (
                f"at price {fmt_price(SCAN_PRICES[i])} on the auction's decisive row (the base "
                f"fish) with buy fraction {SCAN_DEMANDS[f]:g} it {action} ({_scores(scores)})"
            )
        return (
            f"{where}: its two leading scores lie {fmt(lead[p, r], '.2g')} apart (on "
            f"{int(edge[p].sum())} probed items), within {fmt(limits.TIE_MARGIN, 'g')}: the "
            "vote there rests on the last bits of the arithmetic, which the market, computing "
            "the model among other patrons, rounds otherwise"
        )

    return "knife-edge", "B", np.any(edge, axis=1), message


def _non_finite_message(p: int) -> str:
    return "its decision scores B, L, Q are not finite on some probed item: the numbers overflow"


def _buys_cheap(grid: _OnGrid) -> Probe:
    """buys-cheap: the base fish of the preferred sub-type is bought at every f when cheap."""
    base_buys = grid.buys[:, :, BASE_QUALITY, PREFERRED]  # (P, prices, demands)
    cheap_refused = ~base_buys & CHEAP[None, :, None]

    def message(p: int) -> str:
        i, f = _first(cheap_refused[p])
        return (
            f"{grid.at(p, i, BASE_QUALITY, PREFERRED, f)}: it refuses a fish below any "
            "plausible price"
        )

    return "buys-cheap", "B", np.any(cheap_refused, axis=(1, 2)), message


def _buys_something(grid: _OnGrid) -> tuple[Probe, Probe, Probe, Probe]:
    """always-holds, always-quits, never-buys: some probed item is bought; holds-on-most-items:
    at most ``limits.HOLD_SHARE`` of them are held."""
    P = len(grid.buys)
    total = int(np.prod(GRID_SHAPE))
    n_buy = np.count_nonzero(grid.buys.reshape(P, -1), axis=1)
    n_hold = np.count_nonzero(grid.holds.reshape(P, -1), axis=1)
    n_quit = total - n_buy - n_hold
    span = f"{fmt_price(PRICES[0])} to {fmt_price(PRICES[-1])}"

    def message(p: int) -> str:
        return (
            f"on none of the {total} probed items (prices {span}, every quality, sub-type and "
            f"buy fraction) does it buy: it holds on {n_hold[p]} and quits on {n_quit[p]}"
        )

    def most(p: int) -> str:
        return (
            f"it holds on {n_hold[p]} of the {total} probed items (prices {span}, every quality, "
            f"sub-type and buy fraction), more than {limits.HOLD_SHARE:.0%}: it waits for prices "
            f"to fall on nearly everything on sale (it buys {n_buy[p]}, quits {n_quit[p]})"
        )

    most_held = (n_hold > limits.HOLD_SHARE * total) & (n_hold < total)
    return (
        ("always-holds", "L", n_hold == total, message),
        ("always-quits", "Q", n_quit == total, message),
        ("never-buys", "B", (n_buy == 0) & (n_hold < total) & (n_quit < total), message),
        ("holds-on-most-items", "L", most_held, most),
    )


def _far_too_expensive(grid: _OnGrid) -> tuple[Probe, Probe]:
    """refuses-far-too-expensive, quits-far-too-expensive: far above any plausible price the
    base fish is not bought firmly in ordinary demand, and not held at any demand."""
    base_lead = grid.lead[:, :, BASE_QUALITY, PREFERRED]  # (P, prices, demands)
    base_holds = grid.holds[:, :, BASE_QUALITY, PREFERRED]
    firm_buy = base_lead > limits.FIRM_MARGIN
    expensive_buy = firm_buy & FAR_TOO_EXPENSIVE[None, :, None] & ORDINARY[None, None, :]
    expensive_hold = base_holds & FAR_TOO_EXPENSIVE[None, :, None]

    def message(mask: Mask, why: str) -> Callable[[int], str]:
        def explain(p: int) -> str:
            i, f = _first(mask[p])
            return f"{grid.at(p, i, BASE_QUALITY, PREFERRED, f)}: {why}"

        return explain

    return (
        (
            "refuses-far-too-expensive",
            "B",
            np.any(expensive_buy, axis=(1, 2)),
            message(expensive_buy, "it buys firmly far above any plausible price"),
        ),
        (
            "quits-far-too-expensive",
            "L",
            np.any(expensive_hold, axis=(1, 2)),
            message(
                expensive_hold, "it holds far above any plausible price, waiting for it to drop"
            ),
        ),
    )


def _inspected(grid: _OnGrid, scan: Array, finite: Mask) -> list[list[Evidence]]:
    """Each patron's bars that hold it for an inspector when missed (none when its scores
    overflow), from its grid decisions and its scores ``scan`` (P, scan prices, scan demands,
    3) on the decisive row:

    * ``buys-far-below-floor``: the highest scan price at which it buys the base fish in
      ordinary demand, at least ``LOWEST_TOP_BUY`` (measured None: it buys at no scanned price);
      ``detail`` gives its largest buy margin over the prices an auction reaches (the floor
      up), with the price, f and scores there.
    """
    P = len(finite)
    lead, buys, _ = _decisions(scan[:, :, ORDINARY_SCAN])
    bought = buys.any(axis=2)  # (P, scan prices)
    top = np.where(bought, np.arange(len(SCAN_PRICES)), -1).max(axis=1)
    reach = lead[:, REACHABLE].reshape(P, -1)
    reach_at = np.argmax(reach, axis=1)
    reach_i, reach_f = np.unravel_index(reach_at, lead[:, REACHABLE].shape[1:])
    reach_i = reach_i + FLOOR_INDEX
    floor = float(limits.MARKET.threshold_sell_price)
    out: list[list[Evidence]] = []
    for p in range(P):
        if not finite[p]:
            out.append([])
            continue
        j, g = int(reach_i[p]), int(reach_f[p])
        highest = float(SCAN_PRICES[top[p]]) if top[p] >= 0 else None
        best = float(reach[p, reach_at[p]])
        floor_detail: dict[str, object] = {
            "neuron": "B",
            "floor": floor,
            "reachable_buy_margin": best,
            "reachable_price": float(SCAN_PRICES[j]),
            "reachable_buy_fraction": float(SCAN_DEMANDS[ORDINARY_SCAN][g]),
            "lowest_probed": float(SCAN_PRICES[0]),
        }
        passed = highest is not None and highest >= LOWEST_TOP_BUY - 1e-9
        if not passed:
            buys_at = (
                f"it buys only at {fmt_price(highest)} or below"
                if highest is not None
                else f"it buys at no probed price from {fmt_price(SCAN_PRICES[0])} up"
            )
            floor_detail["finding"] = (
                "on the auction's decisive row (the base fish) in ordinary demand (buy fraction "
                f"{limits.ORDINARY_DEMAND:g} or less) {buys_at}, under "
                f"{fmt_price(LOWEST_TOP_BUY)}, far below the stalemate floor "
                f"{fmt_price(floor)}, the lowest price an auction reaches (there its best buy "
                f"margin B − max(L, Q) is {fmt(best, '+.2f')}, at {fmt_price(SCAN_PRICES[j])} "
                f"with buy fraction {SCAN_DEMANDS[ORDINARY_SCAN][g]:g}: "
                f"{_scores(scan[p, j, np.flatnonzero(ORDINARY_SCAN)[g]])}): it can never buy in "
                "an auction, and its copies only lower the buy fraction every voter counts"
            )
        out.append(
            [
                Evidence(
                    "buys-far-below-floor",
                    highest,
                    LOWEST_TOP_BUY,
                    PROBED_PRICE,
                    "at least",
                    passed,
                    floor_detail,
                ),
            ]
        )
    return out


def _buy_falls_with_price(grid: _OnGrid) -> Probe:
    """buy-falls-with-price: the clipped buy margin never swings from refusing to buying as the
    price rises, on any probed item."""
    P = len(grid.lead)
    # The clipped margin's rise over its lowest value at any lower price, price-major
    # (prices, P, items) so that each step of the running minimum is one contiguous operation.
    clipped = grid.lead.clip(-limits.FIRM_MARGIN, limits.FIRM_MARGIN).reshape(P, len(PRICES), -1)
    margin = np.ascontiguousarray(clipped.swapaxes(0, 1))
    lowest = margin.copy()
    for i in range(1, len(PRICES)):
        np.minimum(lowest[i], lowest[i - 1], out=lowest[i])
    rise = margin - lowest
    worst_rise = rise.max(axis=(0, 2))

    def message(p: int) -> str:
        i, q, s, f = _first(rise[:, p].reshape(GRID_SHAPE) == worst_rise[p])
        margins = margin[:, p].reshape(GRID_SHAPE)[:, q, s, f]
        low = int(np.argmin(margins[: i + 1]))
        return (
            f"on {_fish(q, s)} with buy fraction {DEMANDS[f]:g} its buy margin B − max(L, Q) "
            f"rises from {fmt(margins[low], '+.2f')} at price {fmt_price(PRICES[low])} to "
            f"{fmt(margins[i], '+.2f')} at {fmt_price(PRICES[i])} (clipped to "
            f"±{limits.FIRM_MARGIN:g}): it turns from refusing to buying as the price rises"
        )

    return "buy-falls-with-price", "B", worst_rise > limits.MONOTONE_TOLERANCE, message


def _sincere_hold(scan: Array) -> tuple[Probe, Mask, Array, Array]:
    """sincere-hold over the scores ``scan`` (P, scan prices, scan demands, 3) of the decisive
    row, which patrons hold somewhere on its reachable part (P,), and ``hold_gap``."""
    _, scan_buys, scan_holds = _decisions(scan)
    reachable_holds = scan_holds & REACHABLE[None, :, None]  # (P, prices, demands)
    unbacked_at = unbacked_holds(scan_buys, scan_holds)
    unbacked: Mask = np.any(unbacked_at, axis=1)  # (P, demands)

    def message(p: int) -> str:
        f = int(np.flatnonzero(unbacked[p])[0])
        at = int(np.flatnonzero(unbacked_at[p, :, f])[0])
        start = end = at
        while start > FLOOR_INDEX and scan_holds[p, start - 1, f]:
            start -= 1
        while end + 1 < len(SCAN_PRICES) and scan_holds[p, end + 1, f]:
            end += 1
        lower = np.flatnonzero(scan_buys[p, :at, f])
        return (
            f"on the auction's decisive row (the base fish) with buy fraction "
            f"{SCAN_DEMANDS[f]:g} it holds from {fmt_price(SCAN_PRICES[start])} to "
            f"{fmt_price(SCAN_PRICES[end])} (at {fmt_price(SCAN_PRICES[at])}: "
            f"{_scores(scan[p, at, f])}); {_come_down(at)}, and {_would_buy(lower)}: its holds "
            "can never turn into a purchase, they only pull the demand down"
        )

    holds: Mask = np.any(reachable_holds, axis=(1, 2))
    gap, bar = hold_gap(scan_buys, scan_holds)
    return ("sincere-hold", "L", np.any(unbacked, axis=1), message), holds, gap, bar


def unbacked_holds(buys: Mask, holds: Mask) -> Mask:
    """(P, scan prices, demands): the reachable holds of the decisions ``buys``, ``holds`` on
    the decisive-row scan that no purchase backs. A hold at price p is backed when the model
    buys at a price the auction can still come down to from p (``LOWEST_REACHABLE[p]`` up to
    just below p), at the same f."""
    P, n_prices, n_demands = buys.shape
    # bought[:, i]: buys at the first i scan prices
    bought: npt.NDArray[np.intp] = np.zeros((P, n_prices + 1, n_demands), np.intp)
    np.cumsum(buys, axis=1, out=bought[:, 1:])
    backed: Mask = bought[:, np.arange(n_prices)] > bought[:, LOWEST_REACHABLE]
    unbacked: Mask = holds & REACHABLE[None, :, None] & ~backed
    return unbacked


def hold_gap(buys: Mask, holds: Mask) -> tuple[Array, Array]:
    """For each patron, the worst reachable hold of the decisions on the decisive-row scan: how
    far below it the nearest purchase lies (inf: none) and how far the auction can come down
    from it with the slack (the bar), in price; (nan, nan) for a model that never holds. The
    hold is unbacked when the first exceeds the second."""
    P = len(buys)
    prices = SCAN_PRICES[:, None]
    below = np.where(buys, prices, -np.inf)
    # the highest purchase strictly below each price, at the same f
    highest = np.full(buys.shape, -np.inf)
    highest[:, 1:] = np.maximum.accumulate(below, axis=1)[:, :-1]
    reach = (SCAN_PRICES - SCAN_PRICES[LOWEST_REACHABLE])[None, :, None]
    counted = holds & REACHABLE[None, :, None]
    excess = np.where(counted, prices - highest - reach, -np.inf)
    # each patron's worst hold: the first largest excess, price-major
    i, f = np.unravel_index(np.argmax(excess.reshape(P, -1), axis=1), buys.shape[1:])
    holding = counted.reshape(P, -1).any(axis=1)
    gap = np.where(holding, SCAN_PRICES[i] - highest[np.arange(P), i, f], np.nan)
    bar = np.where(holding, reach[0, i, 0], np.nan)
    return gap, bar


def _come_down(at: int) -> str:
    """How far the auction can come down from scan price ``at``."""
    market = limits.MARKET
    slack = limits.HOLD_REACH_SLACK * market.decrement
    floor = SCAN_PRICES[FLOOR_INDEX]
    if at == FLOOR_INDEX:
        return f"{fmt_price(floor)} is the stalemate floor, the lowest price it reaches"
    if SCAN_PRICES[at] <= market.base_price + 1e-9:
        return f"from {fmt_price(SCAN_PRICES[at])} the auction can come down to the floor"
    reach = int(LOWEST_REACHABLE[at])
    return (
        f"from {fmt_price(SCAN_PRICES[at])} the auction can come down only to "
        f"{fmt_price(SCAN_PRICES[reach] + slack)} (once the price has risen above "
        f"{fmt_price(market.base_price)}, a fall of more than "
        f"{fmt_price(market.increment - market.decrement)} ends the auction)"
    )


def _would_buy(lower: npt.NDArray[np.intp]) -> str:
    """Where the holder would buy, from the scan prices ``lower`` below its hold at which it
    buys."""
    slack = limits.HOLD_REACH_SLACK * limits.MARKET.decrement
    buys = (
        f"it would buy only at {fmt_price(SCAN_PRICES[lower[-1]])} or below"
        if len(lower)
        else "it buys at no lower price at all"
    )
    return buys + f" (a purchase up to {fmt_price(slack)} lower still counts)"
