"""Behavioural probes: one clean forward pass of every manifest over a grid of items.

The grid crosses the probe prices (0.3× to 2.5× the base price), three fish qualities
(l = w = g = 0.8, 1, 1.2), all eight sub-types and five previous buy fractions f; augmentation
noise is off (every copy clean), so the probes see the decision the model means. Checks:

* ``buys-cheap``: far below any plausible price, the base fish of the preferred sub-type is
  bought at every f (a rare buyer refuses it unless the others rush or the fish is huge);
* ``always-holds`` / ``always-quits`` / ``never-buys``: some probed item is bought;
* ``refuses-far-too-expensive`` and ``quits-far-too-expensive``: far above any plausible
  price the base fish is not bought firmly in ordinary demand, and not held at any demand
  (holding there means waiting for the price to drop: the saboteur's way to drag the market
  down);
* ``buy-falls-with-price``: the buy margin B − max(L, Q), clipped to a firm decision either
  way, never swings from refusing to buying as the price rises on any probed item;
* ``decisive-row``: on the auction's decisive row (the clean base item (p, 1, 1, 1, ½, ½, ½, f))
  the model does not hold at every price the auction visits, for any f.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from agents.negotiator import FSNBatch, decision_logits
from screener import limits
from screener.findings import Array, Finding, finding, fmt_price
from screener.rules import SUBTYPES

BUY, HOLD, QUIT = range(3)
ACTION_WORDS = ("buys", "holds", "quits")
PRICES = np.array(limits.PROBE_PRICE_FACTORS) * limits.BASE_PRICE
QUALITIES = np.array(limits.PROBE_QUALITIES)
DEMANDS = np.array(limits.PROBE_DEMANDS)
BASE_QUALITY = int(np.flatnonzero(QUALITIES == 1.0)[0])
PREFERRED = 0
"""Index of the preferred sub-type (½, ½, ½) in ``rules.SUBTYPES``."""
GRID_SHAPE = (len(PRICES), len(QUALITIES), len(SUBTYPES), len(DEMANDS))


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
DECISIVE = np.abs(PRICES / limits.BASE_PRICE - np.mean(limits.DECISIVE_WINDOW)) <= (
    np.ptp(limits.DECISIVE_WINDOW) / 2 + 1e-9
)


def _fish(q: int, s: int) -> str:
    quality = {0: "the poorest fish", BASE_QUALITY: "the base fish"}.get(q, "the best fish")
    subtype = ", ".join("½" if v > 0 else "−½" for v in SUBTYPES[s])
    return f"{quality} (l = w = g = {QUALITIES[q]:g}, sub-type ({subtype}))"


def _scores(logits: Array) -> str:
    b, h, q = logits
    return f"B {b:+.2f}, L {h:+.2f}, Q {q:+.2f}"


def probe_findings(batch: FSNBatch) -> list[Finding]:
    """Every behavioural probe over the batch (one forward pass)."""
    with torch.no_grad():
        flat = decision_logits(batch, GRID).numpy()
    P = batch.n_patrons
    logits = flat.reshape(P, *GRID_SHAPE, 3)
    if np.isfinite(flat).all():
        finite, safe = np.ones(P, dtype=bool), logits
    else:
        finite = np.isfinite(flat).reshape(P, -1).all(axis=1)
        safe = np.where(np.isfinite(logits), logits, 0.0)
    action = safe.argmax(axis=-1)  # (P, prices, qualities, sub-types, demands)
    base = action[:, :, BASE_QUALITY, PREFERRED]  # (P, prices, demands)
    base_logits = safe[:, :, BASE_QUALITY, PREFERRED]

    def at(p: int, i: int, q: int, s: int, f: int) -> str:
        return (
            f"at price {fmt_price(PRICES[i])} on {_fish(q, s)} with buy fraction "
            f"{DEMANDS[f]:g} it {ACTION_WORDS[action[p, i, q, s, f]]} "
            f"({_scores(safe[p, i, q, s, f])})"
        )

    def first(mask: Array) -> tuple[int, ...]:
        return tuple(int(v) for v in np.argwhere(mask)[0])

    cheap_refused = (base != BUY) & CHEAP[None, :, None]

    def cheap_message(p: int) -> str:
        i, f = first(cheap_refused[p])
        return (
            f"{at(p, i, BASE_QUALITY, PREFERRED, f)}: it refuses a fish below any plausible price"
        )

    offsets = 3 * np.arange(P)[:, None]
    counts = np.bincount((action.reshape(P, -1) + offsets).ravel(), minlength=3 * P).reshape(P, 3)
    total = int(np.prod(GRID_SHAPE))
    span = f"{fmt_price(PRICES[0])} to {fmt_price(PRICES[-1])}"

    def never_message(p: int) -> str:
        return (
            f"on none of the {total} probed items (prices {span}, every quality, sub-type and "
            f"buy fraction) does it buy: it holds on {counts[p, HOLD]} and quits on "
            f"{counts[p, QUIT]}"
        )

    base_margin = base_logits[..., BUY] - np.maximum(base_logits[..., HOLD], base_logits[..., QUIT])
    firm_buy = base_margin > limits.FIRM_MARGIN
    expensive_buy = firm_buy & FAR_TOO_EXPENSIVE[None, :, None] & ORDINARY[None, None, :]
    expensive_hold = (base == HOLD) & FAR_TOO_EXPENSIVE[None, :, None]

    def expensive_message(mask: Array, why: str) -> Callable[[int], str]:
        def message(p: int) -> str:
            i, f = first(mask[p])
            return f"{at(p, i, BASE_QUALITY, PREFERRED, f)}: {why}"

        return message

    margin = np.clip(
        safe[..., BUY] - np.maximum(safe[..., HOLD], safe[..., QUIT]),
        -limits.FIRM_MARGIN,
        limits.FIRM_MARGIN,
    )  # (P, prices, qualities, sub-types, demands)
    rise = margin - np.minimum.accumulate(margin, axis=1)
    worst_rise = rise.reshape(P, -1).max(axis=1)

    def rise_message(p: int) -> str:
        i, q, s, f = first(rise[p] == worst_rise[p])
        low = int(np.argmin(margin[p, : i + 1, q, s, f]))
        return (
            f"on {_fish(q, s)} with buy fraction {DEMANDS[f]:g} its buy margin B − max(L, Q) "
            f"rises from {margin[p, low, q, s, f]:+.2f} at price {fmt_price(PRICES[low])} to "
            f"{margin[p, i, q, s, f]:+.2f} at {fmt_price(PRICES[i])} (clipped to "
            f"±{limits.FIRM_MARGIN:g}): it turns from refusing to buying as the price rises"
        )

    decisive_hold = (base[:, DECISIVE] == HOLD).all(axis=1)  # (P, demands)
    window = PRICES[DECISIVE]

    def decisive_message(p: int) -> str:
        f = int(np.flatnonzero(decisive_hold[p])[0])
        i = int(np.flatnonzero(DECISIVE)[0])
        return (
            f"on the auction's decisive row (the base fish) with buy fraction {DEMANDS[f]:g} it "
            f"holds at every price from {fmt_price(window[0])} to {fmt_price(window[-1])} "
            f"(at {fmt_price(PRICES[i])}: {_scores(base_logits[p, i, f])}): it would sit in "
            "the auction without buying or quitting, pulling the demand down"
        )

    return [
        finding(
            "probe-non-finite",
            "B",
            ~finite,
            lambda p: (
                "its decision scores B, L, Q are not finite on some probed item: the "
                "numbers overflow"
            ),
        ),
        finding("buys-cheap", "B", finite & cheap_refused.any(axis=(1, 2)), cheap_message),
        finding("always-holds", "L", finite & (counts[:, HOLD] == total), never_message),
        finding("always-quits", "Q", finite & (counts[:, QUIT] == total), never_message),
        finding(
            "never-buys",
            "B",
            finite & (counts[:, BUY] == 0) & (counts[:, HOLD] < total) & (counts[:, QUIT] < total),
            never_message,
        ),
        finding(
            "refuses-far-too-expensive",
            "B",
            finite & expensive_buy.any(axis=(1, 2)),
            expensive_message(expensive_buy, "it buys firmly far above any plausible price"),
        ),
        finding(
            "quits-far-too-expensive",
            "L",
            finite & expensive_hold.any(axis=(1, 2)),
            expensive_message(
                expensive_hold, "it holds far above any plausible price, waiting for it to drop"
            ),
        ),
        finding(
            "buy-falls-with-price",
            "B",
            finite & (worst_rise > limits.MONOTONE_TOLERANCE),
            rise_message,
        ),
        finding("decisive-row", "L", finite & decisive_hold.any(axis=1), decisive_message),
    ]
