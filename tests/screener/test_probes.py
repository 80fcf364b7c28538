"""Behavioural probes: decisions on the probe grid, reported with the input that showed them."""

from __future__ import annotations

import numpy as np

from agents.batch import from_manifests
from agents.forward import decide
from agents.negotiator import honest_manifest, saboteur_manifest
from screener import probes, screen, screen_many
from screener.probes import GRID, GRID_SHAPE, PRICES
from tests.support.corpus import SABOTEURS, edit, honest_corpus
from tests.support.screening import PROBE_RULES, message_of, rules_of


def test_grid_crosses_prices_qualities_subtypes_and_demands():
    assert GRID.shape == (int(np.prod(GRID_SHAPE)), 8)
    assert PRICES[0] == 1.5 and PRICES[-1] == 12.5
    grid = GRID.numpy().reshape(*GRID_SHAPE, 8)
    base = grid[:, 1, 0, 2]  # base quality, preferred sub-type, f = 0.5: the decisive row
    np.testing.assert_allclose(
        base[:, 1:], np.tile([1, 1, 1, 0.5, 0.5, 0.5, 0.5], (len(PRICES), 1))
    )
    np.testing.assert_allclose(base[:, 0], PRICES)


def test_always_hold_saboteur_is_caught_on_the_decisive_row():
    verdict = screen(saboteur_manifest(np.random.default_rng(3), "sab"))
    assert not verdict.accepted
    found = rules_of(verdict)
    assert {("always-holds", "L"), ("sincere-hold", "L"), ("buys-cheap", "B")} <= found
    message = message_of(verdict, "sincere-hold", "L")
    assert message.startswith(
        "on the auction's decisive row (the base fish) with buy fraction 0 it holds from 4.80 "
        "to 6.00"
    )
    assert "4.80 is the stalemate floor, the lowest price it reaches" in message
    assert message.endswith(
        "it buys at no lower price at all (a purchase up to 0.05 lower still counts): its holds "
        "can never turn into a purchase, they only pull the demand down"
    )
    cheap = message_of(verdict, "buys-cheap", "B")
    assert cheap.startswith(
        "at price 1.50 on the base fish (l = w = g = 1, sub-type (½, ½, ½)) with buy fraction 0 "
        "it holds (B -1.00"
    )


def test_never_quitter_passes_every_semantic_rule_and_is_caught_by_a_probe():
    rng = np.random.default_rng(11)
    manifest = edit(honest_manifest(rng, "nq"), SABOTEURS["never-quits"](rng))
    verdict = screen(manifest)
    rules = {rule for rule, _ in rules_of(verdict)}
    assert rules and rules <= PROBE_RULES
    assert "quits-far-too-expensive" in rules
    assert "it holds far above any plausible price" in message_of(
        verdict, "quits-far-too-expensive", "L"
    )


def test_rare_buyer_is_caught_by_the_probes_only():
    rng = np.random.default_rng(5)
    manifest = edit(honest_manifest(rng, "rb"), SABOTEURS["rare-buyer-rush-only"](rng))
    verdict = screen(manifest)
    # it holds at the auction's prices unless the others rush: no hold is backed by a purchase
    assert {rule for rule, _ in rules_of(verdict)} == {"buys-cheap", "sincere-hold"}
    # it does buy the base fish cheaply when everyone else did (f = 1) ...
    batch = from_manifests([manifest])
    cheap_rush = np.array([[1.5, 1, 1, 1, 0.5, 0.5, 0.5, 1.0], [1.5, 1, 1, 1, 0.5, 0.5, 0.5, 0.0]])
    import torch

    assert decide(batch, torch.from_numpy(cheap_rush)).tolist() == [[0, 1]]
    # ... and the reason names the demand where it refuses
    assert "with buy fraction 0 it holds" in message_of(verdict, "buys-cheap", "B")


def test_a_model_that_turns_to_buying_as_the_price_rises(honest):
    dear_lover = edit(honest, {"decision.B.weights.PG": 4.0, "decision.B.bias": -1.0})
    verdict = screen(dear_lover)
    message = message_of(verdict, "buy-falls-with-price", "B")
    assert "rises from -0.75 at price" in message and "to +0.75 at" in message
    assert "it turns from refusing to buying as the price rises" in message
    assert ("refuses-far-too-expensive", "B") in rules_of(verdict)


def test_non_finite_scores_are_reported(honest):
    # at high prices PG ≈ 1, so B ≈ 1e308 + 1e308 overflows to inf
    overflow = edit(honest, {"decision.B.bias": 1e308, "decision.B.weights.PG": 1e308})
    found = rules_of(screen(overflow))
    assert {("probe-non-finite", "B"), ("magnitude", "B")} <= found


def test_batched_screening_equals_one_by_one():
    rng = np.random.default_rng(2)
    manifests = [honest_manifest(rng, f"h{i}") for i in range(3)]
    manifests += [edit(honest_manifest(rng, f"s{i}"), draw(rng))
                  for i, draw in enumerate(list(SABOTEURS.values())[::7])]  # fmt: skip
    manifests.append(saboteur_manifest(rng, "always-hold"))
    together = screen_many(manifests)
    assert together == [screen(m) for m in manifests]
    assert [v.accepted for v in together[:3]] == [True] * 3
    assert not any(v.accepted for v in together[3:])
    assert screen_many([]) == []


def test_mixed_activation_kinds_in_one_batch_score_as_alone(monkeypatch):
    """Manifests whose neurons use different activation kinds share a batch (more than one
    forward pass of PASS_SIZE, here 16) and still get exactly their one-by-one verdicts."""
    monkeypatch.setattr(probes, "PASS_SIZE", 16)
    rng = np.random.default_rng(5)
    honest = [entry.manifest for entry in honest_corpus(rng, 24)]
    below = {"kind": "below_threshold", "a": 5.0, "c": 0.5, "negative_slope": 0.01}  # SZ
    odd = [
        edit(honest_manifest(rng, f"k{i}"), {"external_sensor.SZ.activation": below})
        for i in range(12)
    ]
    manifests = [m for pair in zip(honest, odd, strict=False) for m in pair] + honest[12:]
    assert len(manifests) > 2 * probes.PASS_SIZE
    assert screen_many(manifests) == [screen(m) for m in manifests]


def test_a_model_holding_on_nearly_everything_but_the_base_fish_is_refused() -> None:
    """A red team's holder buys the base fish in an admitted bargainer's window and holds on
    every other item (the rows whose buy fractions feed the honest patrons' fine-tuning): its
    harm was 0.81-0.84 of a saboteur's with fine-tuning. Honest models hold on at most 0.349
    of the probed items."""
    from pathlib import Path

    from agents.manifest import parse_manifest_json
    from screener import screen

    path = Path(__file__).parents[1] / "support" / "red_team" / "row-keyed-window-holder.json"
    verdict = screen(parse_manifest_json(path.read_text()))
    # (its price sensor's peak is narrower than its noise too, at a buy fraction between the
    # noisy scan's: the gate, read at every buy fraction, names it as well)
    assert rules_of(verdict) == {("holds-on-most-items", "L"), ("noise-gate", "PG")}
    assert message_of(verdict, "holds-on-most-items", "L").startswith(
        "it holds on 2650 of the 2760 probed items"
    )
