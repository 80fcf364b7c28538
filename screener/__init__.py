"""The inspector: reads a submitted manifest weight by weight, probes its behaviour and, when it
holds out for lower prices, measures what it would do to an auction.

``screen(manifest) -> Verdict`` is the one entry point for a single model (``/submit``,
``srd screen``, ``srd auction-study --screen``); ``screen_many`` judges a whole batch at once
with the same verdict for each manifest as ``screen``. ``rescreen`` is the one re-screening of
fine-tuned patrons (a ``sim.market.RescreenBatch``, used by the server's auctions and by the
study alike), ``rescreen_many`` the same judgement for manifests.

A manifest is accepted when nothing finds anything:

* the semantic rules (``screener.rules``) read each named weight against the meaning the paper
  gives its neuron;
* the behavioural probes (``screener.probes``) watch its decisions on a grid of items, and on
  the auction's decisive row at every price the market can reach: each hold must be backed by a
  purchase at a price the auction can still come down to (the sincere-hold rule);
* the noisy scan (``screener.noisy``) watches the decisive row again as the market evaluates it,
  on the model's own noisy copies: the sincere-hold rule there, and no band where the noise
  flips a purchase into a hold;
* the market-impact test (``screener.impact``), for models that hold somewhere on the decisive
  row, clean or on their noisy copies: copies of the model in small counterfactual auctions must
  not pull the mean purchase price down more than copies that simply quit do, plus a quarter of
  what always-hold saboteurs do (the price alone: test auctions that sell nothing are no
  evidence about it, docs/screener.md, *Copies that stall the market*).

At the door (``screen``, ``screen_many``) a model with fine-tuning settings is also fine-tuned
alone through a reference auction's rounds (as many as an auction runs), unchecked, and that
version must pass the rules, probes and noisy scan (``fine-tuning-drift``) and, if it holds, the
market-impact test; re-screening (``rescreen``) skips this, since every later fine-tuning round
is re-screened in its turn. Every verdict carries the numbers of the bars the model was held to
(``Evidence``); ``review`` turns it into accepted, refused or held for a margin in price. Three
bars hold a model for an inspector instead of refusing it (``verdict.INSPECTED``): a keen
buyer far above any plausible price in ordinary demand, or where most voters bought (clean or
on its noisy copies), and a bidder that buys only far below the lowest price an auction
reaches. Every
threshold is in ``screener.limits`` with its rationale. The judging modules (and torch) are
imported when a model is first judged: the API process reads ``Verdict`` without them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from screener.verdict import PRICE, Evidence, Reason, Verdict, review, with_hold_reasons

if TYPE_CHECKING:
    from agents.batch import FSNBatch
    from agents.manifest import Manifest
    from screener.checks import Cheap
    from screener.findings import Checks

__all__ = [
    "Evidence",
    "Reason",
    "Verdict",
    "judge",
    "rescreen",
    "rescreen_many",
    "review",
    "screen",
    "screen_many",
    "with_hold_reasons",
]


def judge(batch: FSNBatch, *, at_the_door: bool) -> list[Verdict]:
    """Verdicts for a batch of models; ``at_the_door`` also judges each model's own
    fine-tuning (see the module docstring). Nothing is differentiated: the judging runs in
    torch's inference mode (no autograd bookkeeping on its many small tensor operations)."""
    import torch

    with torch.inference_mode():
        return _judge(batch, at_the_door=at_the_door)


def _judge(batch: FSNBatch, *, at_the_door: bool) -> list[Verdict]:
    from screener.checks import cheap_checks, failed_any
    from screener.findings import check
    from screener.impact import impact_checks, project

    cheap = cheap_checks(batch)
    groups = list(cheap.groups)
    passed = ~failed_any(groups)
    evidence = _scan_evidence(cheap, range(batch.n_patrons), "")
    projected: list[tuple[int, FSNBatch]] = []
    if at_the_door:
        tunes = passed & (batch.epochs.numpy() > 0) & (batch.learning_rate.numpy() > 0)
        index = np.flatnonzero(tunes)
        drift = np.zeros(batch.n_patrons, dtype=np.bool_)
        words: dict[int, str] = {}
        if len(index):
            tuned = cheap_checks(project(batch.select(index)))
            refused = failed_any(tuned.groups)
            for k in np.flatnonzero(refused):
                p = int(index[k])
                drift[p] = True
                words[p] = _drift_message(batch, p, tuned.groups, int(k))
                evidence[p] += _drift_evidence(tuned, int(k))
            projected = [
                (int(index[k]), tuned.batch.select([int(k)]))
                for k in np.flatnonzero(tuned.holds & ~refused)
            ]
        groups.append(check("fine-tuning-drift", "T", drift, words.__getitem__))
    tested = np.flatnonzero(passed & cheap.holds).tolist()
    impact, measured = impact_checks(batch, tested, projected)
    groups.append(impact)
    for p, items in measured.items():
        evidence[p] += items
    return _verdicts(groups, evidence)


PRICED_CHECKS = ("sincere-hold", "noise-gated-hold", "noise-flip")
"""The cheap checks measured in price (the others are pass or fail)."""


def _scan_evidence(cheap: Cheap, patrons: Sequence[int], test: str) -> list[list[Evidence]]:
    """Each model's (of ``patrons``) decisive-row bars: its worst hold's distance down to a
    purchase against the reach allowed there, clean (``sincere-hold``) and as the market sees
    it (``noise-gated-hold``), and the widest band its noise flips from buying to holding
    (``noise-flip``, with the decisions at the base buy fraction with and without noise); and
    the bars that hold it for an inspector (``probes.Probed.inspected``,
    ``noisy.Noisy.inspected``). ``test`` set: the
    priced bars under that name (a fine-tuned version's, only the failed ones; the projection
    is not held for an inspector)."""
    from screener import limits
    from screener.noisy import decisions_in_words

    probed, noisy, batch = cheap.probed, cheap.noisy, cheap.batch
    failing = {
        rule: np.any(group.failed[:, [k for k, r in enumerate(group.rules) if r == rule]], axis=1)
        for group in cheap.groups
        for rule in PRICED_CHECKS
        if rule in group.rules
    }
    index = np.asarray(patrons, dtype=np.intp)
    failed = {rule: mask[index].tolist() for rule, mask in failing.items()}
    gap, bar = probed.gap[index].tolist(), probed.bar[index].tolist()
    noisy_gap, noisy_bar = noisy.gap[index].tolist(), noisy.bar[index].tolist()
    flips = noisy.flip[index].tolist()
    copies, noise_std = batch.copies[index].tolist(), batch.noise_std[index].tolist()
    out: list[list[Evidence]] = []
    for n, p in enumerate(index.tolist()):
        found: list[Evidence] = []
        words = {
            "buy_fraction": 0.5,
            "clean": decisions_in_words(noisy.clean[p], 0.5),
            "noisy": decisions_in_words(noisy.noisy[p], 0.5),
            "copies": copies[n],
            "noise_std": noise_std[n],
            "draws": limits.NOISE_DRAWS,
        }
        for rule, measured, reach, detail in (
            ("sincere-hold", gap[n], bar[n], {}),
            ("noise-gated-hold", noisy_gap[n], noisy_bar[n], words),
        ):
            if np.isnan(reach):
                continue
            detail = {**detail, "check": rule} if test else detail
            found.append(
                Evidence(  # prices: differences on the scan's cent grid, read to 1e-10
                    test or rule,
                    None if np.isinf(measured) else round(measured, 10),
                    round(reach, 10),
                    PRICE,
                    "at most",
                    not failed[rule][n],
                    detail,
                )
            )
        flip_detail = {**words, "check": "noise-flip"} if test else words
        found.append(
            Evidence(
                test or "noise-flip",
                flips[n],
                limits.NOISE_FLIP_BAND,
                PRICE,
                "at most",
                not failed["noise-flip"][n],
                flip_detail,
            )
        )
        if not test:
            found += probed.inspected[p] + noisy.inspected[p]
        out.append([e for e in found if not (test and e.passed)])
    return out


def _drift_evidence(tuned: Cheap, k: int) -> list[Evidence]:
    """Why the fine-tuned version k failed, as bars: the priced decisive-row bars it missed,
    and every other check it failed (no bar in price: measured and bar None)."""
    (found,) = _scan_evidence(tuned, [k], "fine-tuning-drift")
    for group in tuned.groups:
        for c in np.flatnonzero(group.failed[k]):
            rule = group.rules[int(c)]
            if rule not in PRICED_CHECKS:
                detail = {"check": rule, "neuron": group.neurons[int(c)]}
                found.append(
                    Evidence("fine-tuning-drift", None, None, "check", "at most", False, detail)
                )
    return found


def _drift_message(batch: FSNBatch, p: int, tuned: list[Checks], k: int) -> str:
    """Why model p's projected fine-tuned version (row k of ``tuned``) is refused."""
    from screener.impact import rounds

    group, column = next((g, c) for g in tuned for c in range(len(g.rules)) if g.failed[k, c])
    return (
        f"after {rounds()} rounds of its own fine-tuning in a reference auction (lr "
        f"{float(batch.learning_rate[p]):.3g}, {int(batch.epochs[p])} epochs, batch "
        f"{int(batch.batch_size[p])}), its PFC's verdicts T/F have made it fail "
        f"'{group.rules[column]}' ({group.neurons[column]}): {group.message(column, k)}"
    )


def _verdicts(groups: list[Checks], evidence: list[list[Evidence]]) -> list[Verdict]:
    failed = np.concatenate([g.failed for g in groups], axis=1)  # (P, checks)
    reasons: list[list[Reason]] = [[] for _ in evidence]
    if failed.any():
        checks: list[tuple[Checks, int]] = [(g, k) for g in groups for k in range(len(g.rules))]
        for p, column in zip(*np.nonzero(failed), strict=True):
            group, k = checks[column]
            reasons[p].append(Reason(group.rules[k], group.neurons[k], group.message(k, int(p))))
    return [
        Verdict(accepted=not r, reasons=r, evidence=e)
        for r, e in zip(reasons, evidence, strict=True)
    ]


def screen_many(manifests: Sequence[Manifest]) -> list[Verdict]:
    """Judge parsed manifests together at the door; one verdict each, in order."""
    from agents.batch import from_manifests

    if not manifests:
        return []
    return judge(from_manifests(manifests), at_the_door=True)


def screen(manifest: Manifest) -> Verdict:
    """Judge one parsed manifest: accepted, or rejected with every reason in plain words."""
    return screen_many([manifest])[0]


def rescreen_many(manifests: Sequence[Manifest]) -> list[Verdict]:
    """Judge fine-tuned versions of admitted models (inside an auction that re-screens every
    round); one verdict each, in order."""
    from agents.batch import from_manifests

    if not manifests:
        return []
    return judge(from_manifests(manifests), at_the_door=False)


def rescreen(patrons: FSNBatch) -> npt.NDArray[np.bool_]:
    """The market's re-screening of the patrons a fine-tuning round moved
    (``sim.market.RescreenBatch``): True keeps a patron's new version, False reverts it."""
    return np.array([v.accepted for v in judge(patrons, at_the_door=False)], dtype=np.bool_)
