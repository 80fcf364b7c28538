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
   that row: of every voter (``buy_fraction`` "all", the paper's) or of those who voted buy
   or hold on it ("staying": quitting does not lower f). Row-0 quitters leave.
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

Modules, one job each:

* ``config``: ``MarketConfig`` (the rules), ``fish_on_sale`` and what the rules say of an
  iteration;
* ``items``: the item rows, the prototype fish and its variations;
* ``randomness``: every random stream of an auction, derived from its seed;
* ``records``: ``IterationRecord``, what an iteration reports;
* ``engine``: ``MarketBatch``, the lock-step iteration (votes, price rules, rows, stops,
  fine-tuning and re-screening);
* ``design``: what a remote fine-tuning round's update may change (weights and biases only);
* ``rounds``: the remote fine-tuning rounds (``FineTuneRound``, closing one);
* ``checkpoint``: a batch's state and its bytes, to continue bit for bit;
* ``auction``: ``Market``, one auction.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sim.market.auction import Market
    from sim.market.config import (
        BuyFractionRule,
        FineTuneMode,
        MarketConfig,
        fine_tunes_after,
        fish_on_sale,
        scores_all_rows,
    )
    from sim.market.design import design_changes, round_update_problems
    from sim.market.engine import MarketBatch, Rescreen, RescreenBatch, single_thread
    from sim.market.items import item_rows
    from sim.market.randomness import AuctionRandom, round_seeds
    from sim.market.records import IterationRecord
    from sim.market.rounds import FineTuneRound

_HOMES = {
    "AuctionRandom": "randomness",
    "BuyFractionRule": "config",
    "FineTuneMode": "config",
    "FineTuneRound": "rounds",
    "IterationRecord": "records",
    "Market": "auction",
    "MarketBatch": "engine",
    "MarketConfig": "config",
    "Rescreen": "engine",
    "RescreenBatch": "engine",
    "design_changes": "design",
    "fine_tunes_after": "config",
    "fish_on_sale": "config",
    "item_rows": "items",
    "round_seeds": "randomness",
    "round_update_problems": "design",
    "scores_all_rows": "config",
    "single_thread": "engine",
}
"""Each name of the package and the module it lives in. A name is imported on first use, so
the rules (``config``, ``design``) come without torch: the API process reads them and never
loads the engine."""

__all__ = [
    "AuctionRandom",
    "BuyFractionRule",
    "FineTuneMode",
    "FineTuneRound",
    "IterationRecord",
    "Market",
    "MarketBatch",
    "MarketConfig",
    "Rescreen",
    "RescreenBatch",
    "design_changes",
    "fine_tunes_after",
    "fish_on_sale",
    "item_rows",
    "round_seeds",
    "round_update_problems",
    "scores_all_rows",
    "single_thread",
]
assert set(__all__) == set(_HOMES), "every name of the package has its home"


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'sim.market' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"sim.market.{home}"), name)
    globals()[name] = value
    return value
