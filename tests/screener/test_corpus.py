"""The labelled corpus: honest models (paper randomisation, fine-tuned, sensible variants) and
hand-written sincere variants are accepted (≥ 99.5%), saboteur constructions of every kind and
the red team's disguised saboteurs rejected (≥ 99%, every kind caught), each rejection naming a
neuron. The default run screens a smaller seeded corpus; the full one is slow-marked."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from screener import review, screen_many
from server.config import Settings
from tests.support.corpus import (
    RED_TEAM_SINCERE,
    SABOTEURS,
    SINCERE,
    Labelled,
    corpus,
    red_team_corpus,
    sincere_corpus,
)
from tests.support.screening import KNOWN_NEURONS

MARGIN = Settings.model_fields["review_margin"].default
"""The server's default review margin (SRD_REVIEW_MARGIN)."""

SEED = 0


def labelled(n_honest: int, per_sincere: int, per_saboteur: int) -> list[Labelled]:
    entries = corpus(SEED, n_honest, per_saboteur)
    entries += sincere_corpus(np.random.default_rng([SEED, 1]), per_sincere)
    return entries + red_team_corpus()


def judge(entries: list[Labelled]) -> list[tuple[Labelled, object]]:
    verdicts = []
    for start in range(0, len(entries), 64):
        verdicts += screen_many([e.manifest for e in entries[start : start + 64]])
    return list(zip(entries, verdicts, strict=True))


def check_targets(judged, per_saboteur: int) -> None:
    honest = [v.accepted for e, v in judged if not e.saboteur]
    caught = [not v.accepted for e, v in judged if e.saboteur]
    assert sum(honest) / len(honest) >= 0.995
    assert sum(caught) / len(caught) >= 0.99
    missed = Counter(e.construction for e, v in judged if e.saboteur and v.accepted)
    assert not [kind for kind, n in missed.items() if n == per_saboteur]
    # The red team's saboteurs: none is admitted by a server at the default review margin (one,
    # a blind-size holder, lands 0.004 above the bar over 96 auctions and is held for an
    # inspector); its sincere models are all accepted.
    red_team = [(e, v) for e, v in judged if e.construction.startswith("red-team:")]
    assert red_team and all(
        review(v, MARGIN) != "accepted" if e.saboteur else v.accepted for e, v in red_team
    )
    for _, verdict in judged:
        if verdict.accepted:
            assert verdict.reasons == []
            continue
        assert verdict.reasons
        for reason in verdict.reasons:
            assert reason.neuron in KNOWN_NEURONS
            assert len(reason.message) > 40 and reason.rule


@pytest.fixture(scope="module")
def small():
    return judge(labelled(n_honest=300, per_sincere=12, per_saboteur=3))


def test_corpus_has_every_kind(small):
    kinds = {(e.saboteur, e.construction) for e, _ in small}
    assert {(True, k) for k in SABOTEURS} <= kinds
    assert {(False, k) for k in SINCERE} <= kinds
    assert {(False, f"red-team:{k}") for k in RED_TEAM_SINCERE} <= kinds
    assert sum(1 for sab, k in kinds if sab and k.startswith("red-team:")) >= 5


def test_targets_on_the_seeded_corpus(small):
    check_targets(small, per_saboteur=3)


@pytest.mark.slow
def test_targets_on_the_full_seeded_corpus():
    check_targets(judge(labelled(n_honest=1000, per_sincere=40, per_saboteur=8)), per_saboteur=8)


LOW_VALUATION = ("variant-wtp", "variant-mixed-fine-tuned")
"""Honest kinds whose willingness to pay is drawn down to 2.6: those drawn under about 4 buy
only far below the floor, as the red team's never-buyer does, and are held for an inspector."""


def inspector_holds(judged) -> Counter[tuple[str, str]]:
    """The honest models the screener accepts and a server holds on a missed inspection bar
    (``keen-far-too-expensive``, ``buys-far-below-floor``), by kind and bar."""
    return Counter(
        (e.construction, ev.test)
        for e, v in judged
        if not e.saboteur and v.accepted and review(v, MARGIN) == "held"
        for ev in v.evidence
        if ev.inspected()
    )


def test_inspector_holds_only_low_valuations_and_keen_buyers(small):
    held = inspector_holds(small)
    assert {kind for kind, _ in held} <= {*LOW_VALUATION, "sincere-keen-buyer"}
    assert all(test == "buys-far-below-floor" for kind, test in held if kind in LOW_VALUATION)


@pytest.mark.slow
def test_inspector_holds_on_the_full_seeded_corpus():
    # measured (docs/screener.md): of 1481 honest and sincere models, 20 low-valuation variants
    # (highest purchase 2.70-3.90) and 1 of 40 sincere keen buyers (0.58 at 12.50)
    judged = judge(labelled(n_honest=1000, per_sincere=40, per_saboteur=8))
    assert inspector_holds(judged) == {
        ("variant-wtp", "buys-far-below-floor"): 12,
        ("variant-mixed-fine-tuned", "buys-far-below-floor"): 8,
        ("sincere-keen-buyer", "keen-far-too-expensive"): 1,
    }
