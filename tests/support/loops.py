"""The reference loops, written plainly one patron at a time: what the batched engines must equal.

* ``loop_fine_tune``: per-patron SRD with autograd (its own epochs and shuffles, batches of its
  size, SGD), against which ``agents.fine_tuning.fine_tune`` is checked;
* ``loop_auction``: the auction as the reference's server loop runs it, against which
  ``sim.market.MarketBatch`` is checked (and timed in ``benchmarks/market.py``).
"""

from __future__ import annotations

import torch

from agents.batch import from_manifests, to_manifest
from agents.fine_tuning import derive_seeds, draw_fine_tune_seeded
from agents.forward import decide, make_noise, self_reward
from agents.manifest import Manifest
from agents.neurons import self_reward_loss
from sim.market import (
    AuctionRandom,
    IterationRecord,
    MarketConfig,
    fine_tunes_after,
    item_rows,
    round_seeds,
    scores_all_rows,
)


def loop_fine_tune(manifest: Manifest, x, order, noise) -> Manifest:
    """Plain per-patron SRD: its own epochs and shuffles, batches of its size, SGD."""
    batch = from_manifests([manifest])
    params = {k: v.clone() for k, v in batch.parameters().items()}
    cfg = manifest.fine_tuning
    pfc = {"judgement_weight", "judgement_bias", "verdict_weight", "verdict_bias"}
    for epoch in range(cfg.epochs):
        perm = order[epoch]
        for start in range(0, x.shape[0], cfg.batch_size):
            rows = perm[start : start + cfg.batch_size]
            live = {k: v.requires_grad_(True) for k, v in params.items()}
            z = self_reward(batch.with_parameters(live), x[rows], noise[None, epoch, rows])
            grads = torch.autograd.grad(self_reward_loss(z), list(live.values()))
            with torch.no_grad():
                params = {}
                for (k, v), g in zip(live.items(), grads, strict=True):
                    frozen = k in pfc and not manifest.pfc.trainable
                    params[k] = v if frozen else v - cfg.learning_rate * g
    return to_manifest(batch.with_parameters({k: v.detach() for k, v in params.items()}), 0)


def loop_auction(manifests: list[Manifest], config: MarketConfig) -> list[IterationRecord]:
    """The auction written plainly, one patron at a time (the reference's server loop).

    It draws the same random numbers as the engine: the rows and price raises from the numpy
    generator, row 0's noise from ``decisive``, rows 1.. from ``rows``, each drawn for the
    active patrons in order and sliced per patron here; fine-tuning from each patron's own
    generators, seeded from the round's seeds and its position.
    """
    random = AuctionRandom.from_seed(config.seed)
    rows = torch.tensor(item_rows(config, random.numpy))
    R = config.n_rows
    everyone = from_manifests(manifests)
    current = list(manifests)
    singles = [from_manifests([m]) for m in manifests]
    active = list(range(len(manifests)))
    price, threshold, available = config.base_price, config.threshold_sell_price, config.n_fish
    records = []
    for iteration in range(config.max_iterations):
        width = R if scores_all_rows(config, iteration) else 1
        group = everyone.select(active)
        noise = make_noise(group, 1, random.decisive)
        if width > 1:
            noise = torch.cat((noise, make_noise(group, R - 1, random.rows)), dim=1)
        decisions = {}
        for j, p in enumerate(active):
            copies = current[p].augmentation.copies
            own = noise[j : j + 1, :, :copies]
            decisions[p] = decide(singles[p], rows[:width], own)[0].tolist()
        row0 = [decisions[p][0] for p in active]
        votes = {name: row0.count(code) for code, name in enumerate(("buy", "hold", "quit"))}
        every = [d for p in active for d in decisions[p]]
        row_votes = {name: every.count(code) for code, name in enumerate(("buy", "hold", "quit"))}
        counted = [
            sum(
                decisions[p][r] in ((0, 1) if config.buy_fraction == "staying" else (0, 1, 2))
                for p in active
            )
            for r in range(width)
        ]
        fractions = [
            sum(decisions[p][r] == 0 for p in active) / max(counted[r], 1) for r in range(width)
        ]
        start_price, start_available = price, available
        buyers = []
        if votes["buy"] > available:
            threshold = price + config.decrement
            price = price + config.increment - random.numpy.uniform(0, 4) * config.decrement
        else:
            buyers = [(p, start_price) for p in active if decisions[p][0] == 0]
            available -= votes["buy"]
            price = price - config.decrement
        quitters = [p for p in active if decisions[p][0] == 2]
        gone = set(quitters) | {p for p, _ in buyers}
        active = [p for p in active if p not in gone]
        rows[:, 0] = price
        rows[:width, 7] = torch.tensor(fractions, dtype=torch.float64)
        reason = None
        if available == 0:
            reason = "sold_out"
        elif not active:
            reason = "no_patrons"
        elif price < threshold:
            reason = "stalemate"
        elif iteration + 1 >= config.max_iterations:
            reason = "max_iterations"
        tuned = []
        if reason is None and fine_tunes_after(config, iteration):
            tuned = loop_fine_tune_round(current, active, rows, round_seeds(config.seed, iteration))
            for p in tuned:
                singles[p] = from_manifests([current[p]])
        records.append(
            IterationRecord(  # prices as the reference records them: rounded to 5 decimals
                iteration=iteration,
                price=round(start_price, 5),
                n_available=start_available,
                votes=votes,
                row_votes=row_votes,
                buyers=[(p, round(paid, 5)) for p, paid in buyers],
                quitters=quitters,
                next_price=round(price, 5),
                n_available_after=available,
                finished=reason is not None,
                stop_reason=reason,
                fine_tuned=tuned,
            )
        )
        if reason is not None:
            break
    return records


def loop_fine_tune_round(
    current: list[Manifest], active: list[int], rows: torch.Tensor, seeds: tuple[int, int]
) -> list[int]:
    """Fine-tune every active patron with epochs in place, one at a time, from its own
    generators (the round's shuffle and noise seeds and its position); the positions tuned."""
    shuffle_seed, noise_seed = seeds
    tuned = []
    for p in active:
        if current[p].fine_tuning.epochs > 0:
            own = draw_fine_tune_seeded(
                from_manifests([current[p]]),
                rows.shape[0],
                derive_seeds(shuffle_seed, p),
                derive_seeds(noise_seed, p),
            )
            current[p] = loop_fine_tune(current[p], rows, own.order[0], own.noise[0])
            tuned.append(p)
    return tuned
