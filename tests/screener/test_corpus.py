"""The labelled corpus: honest models (paper randomisation, fine-tuned, sensible variants) are
accepted, saboteur constructions of every kind rejected, each rejection naming a neuron."""

from __future__ import annotations

from collections import Counter

import pytest

from screener import screen_many
from tests.screener.corpus import SABOTEURS, corpus
from tests.screener.test_rules import KNOWN_NEURONS

SEED = 0
N_HONEST = 1000
PER_SABOTEUR_KIND = 8


@pytest.fixture(scope="module")
def judged():
    entries = corpus(SEED, N_HONEST, PER_SABOTEUR_KIND)
    verdicts = []
    for start in range(0, len(entries), 128):
        verdicts += screen_many([e.manifest for e in entries[start : start + 128]])
    return list(zip(entries, verdicts, strict=True))


def test_corpus_has_every_kind_in_size(judged):
    kinds = Counter((e.saboteur, e.construction) for e, _ in judged)
    honest = sum(n for (sab, _), n in kinds.items() if not sab)
    saboteurs = sum(n for (sab, _), n in kinds.items() if sab)
    assert honest >= N_HONEST
    assert saboteurs == PER_SABOTEUR_KIND * (len(SABOTEURS) + 1)
    assert {"honest-fine-tuned", "honest-fine-tuned-max", "variant-mixed-fine-tuned"} <= {
        c for (sab, c) in kinds if not sab
    }


def test_honest_models_are_accepted_and_saboteurs_rejected(judged):
    honest = [v.accepted for e, v in judged if not e.saboteur]
    caught = [not v.accepted for e, v in judged if e.saboteur]
    assert sum(honest) / len(honest) >= 0.995
    assert sum(caught) / len(caught) >= 0.99
    missed = Counter(e.construction for e, v in judged if e.saboteur and v.accepted)
    assert not [kind for kind, n in missed.items() if n == PER_SABOTEUR_KIND]


def test_every_rejection_names_a_neuron_in_plain_words(judged):
    for _, verdict in judged:
        if verdict.accepted:
            assert verdict.reasons == []
            continue
        assert verdict.reasons
        for reason in verdict.reasons:
            assert reason.neuron in KNOWN_NEURONS
            assert len(reason.message) > 40 and reason.rule
