"""The Fish Sale Negotiator: designed numbers, batching, augmentation, fine-tuning, factories."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from agents.batch import from_manifests, to_manifest
from agents.fine_tuning import draw_fine_tune, fine_tune
from agents.forward import (
    NEURONS,
    activations,
    clean_logits,
    decide,
    decision_logits,
    make_noise,
    self_reward,
)
from agents.manifest import Manifest
from agents.negotiator import honest_manifest, saboteur_manifest
from tests.support.loops import loop_fine_tune

# The reference's values: D = 1, no noise, hold_bias = quit_bias = 0.
REFERENCE_TABLE = [
    # b, p, PG, SZ, LSR, ST, B, L, Q, T, F
    (4.8, 4.9, 0.377, 0.040, 0.009, 0.586, 1.258, 0.262, 0.254, 0.416, 0.472),
    (4.8, 5.0, 0.671, 0.040, 0.009, 0.581, 0.959, 0.497, 0.843, 0.336, 0.511),
    (4.8, 5.2, 0.928, 0.041, 0.010, 0.569, 0.692, 0.702, 1.357, 0.271, 0.544),
    (5.0, 4.9, -0.004, 0.040, 0.009, 0.586, 1.639, -0.043, -0.508, 0.512, 0.417),
    (5.0, 5.0, -0.0002, 0.040, 0.0095, 0.581, 1.630, -0.040, -0.500, 0.511, 0.418),
    (5.0, 5.1, 0.363, 0.041, 0.010, 0.575, 1.262, 0.250, 0.225, 0.418, 0.470),
    (5.0, 5.2, 0.653, 0.041, 0.010, 0.569, 0.967, 0.481, 0.805, 0.340, 0.508),
]


def edited(manifest: Manifest, edit) -> Manifest:
    data = manifest.model_dump(mode="json")
    edit(data)
    return Manifest.model_validate(data)


def reference_patron(b: float, copies: int = 1) -> Manifest:
    def edit(d):
        d["external_sensor"]["PG"]["weights"]["price"] = 1.0 / b
        d["decision"]["L"]["bias"] = 0.0
        d["decision"]["Q"]["bias"] = -0.5
        d["augmentation"]["copies"] = copies

    return edited(honest_manifest(np.random.default_rng(0), "ref"), edit)


def item(price: float, f: float = 0.5) -> list[float]:
    return [price, 1.0, 1.0, 1.0, 0.5, 0.5, 0.5, f]


def test_every_neuron_matches_the_reference_table():
    for b, p, *expected in REFERENCE_TABLE:
        batch = from_manifests([reference_patron(b)])
        act = activations(batch, torch.tensor([item(p)], dtype=torch.float64))
        got = [float(act[n][0, 0]) for n in ("PG", "SZ", "LSR", "ST", "B", "L", "Q", "T", "F")]
        assert got == pytest.approx(expected, abs=1e-3), (b, p)


def test_designed_sensor_numbers_by_hand():
    # b = 4.8, p = 4.9: PG = T(p/b − 3δ + 1.5δ + 0.5δ; a=20, c=1).
    batch = from_manifests([reference_patron(4.8)])
    act = activations(batch, torch.tensor([item(4.9)], dtype=torch.float64))
    pre_pg = 4.9 / 4.8 - 0.003 + 0.0015 + 0.0005
    assert float(act["PG"][0, 0]) == pytest.approx(math.tanh(20 * (pre_pg - 1)), abs=1e-12)
    pre_st = 0.001 * (4.9 + 3 + 0.5) + 0.5 - 0.5
    assert float(act["ST"][0, 0]) == pytest.approx(1e-4 / (1e-4 + pre_st**2), abs=1e-12)
    # B = −PG + SZ + LSR + ST + 1, exactly the FC of the designed weights.
    b = -act["PG"] + act["SZ"] + act["LSR"] + act["ST"] + 1.0
    torch.testing.assert_close(act["B"], b, rtol=0, atol=1e-12)
    # PGL = softmax_PG + softmax_L over [PG, SZ, LSR, ST, B, L, Q].
    sources = torch.stack([act[n][0, 0] for n in ("PG", "SZ", "LSR", "ST", "B", "L", "Q")])
    soft = torch.softmax(sources, 0)
    assert float(act["PGL"][0, 0]) == pytest.approx(float(soft[0] + soft[5]), abs=1e-12)
    assert float(act["T"][0, 0]) == pytest.approx(
        math.tanh(float(act["PGL"][0, 0])) + math.tanh(float(act["BC"][0, 0])), abs=1e-12
    )


def mixed_manifests() -> list[Manifest]:
    """Five patrons with different activations, copies and noise settings."""
    rng = np.random.default_rng(7)
    base = [honest_manifest(rng, f"h{i}") for i in range(4)] + [saboteur_manifest(rng, "s")]

    def exotic(d):
        d["external_sensor"]["SZ"]["activation"] = {"kind": "selective", "epsilon": 0.05}
        d["external_sensor"]["LSR"]["activation"] = {
            "kind": "below_threshold",
            "a": 3.0,
            "c": 0.4,
            "negative_slope": 0.2,
        }
        d["external_sensor"]["ST"]["activation"] = {
            "kind": "threshold",
            "a": 2.0,
            "c": 0.0,
            "negative_slope": 0.1,
        }
        d["augmentation"] = {"copies": 3, "noise_std": 0.05, "noiseless_inputs": ["price"]}

    def single_copy(d):
        d["augmentation"]["copies"] = 1

    base[1] = edited(base[1], exotic)
    base[2] = edited(base[2], single_copy)
    return base


def test_heterogeneous_batch_equals_patron_by_patron():
    manifests = mixed_manifests()
    batch = from_manifests(manifests)
    gen = torch.Generator().manual_seed(3)
    x = torch.tensor([item(4.7 + 0.1 * i, 0.1 * i) for i in range(6)], dtype=torch.float64)
    x[:, 1:4] += 0.1 * torch.randn((6, 3), generator=gen, dtype=torch.float64)
    noise = make_noise(batch, 6, gen)
    assert noise.shape == (5, 6, 5, 8)
    together = activations(batch, x, noise)
    for p, m in enumerate(manifests):
        alone = from_manifests([m])
        own = noise[p : p + 1, :, : m.augmentation.copies]
        single = activations(alone, x, own)
        for name in NEURONS:
            torch.testing.assert_close(together[name][p], single[name][0], rtol=0, atol=1e-12)
    logits = decision_logits(batch, x, noise)
    torch.testing.assert_close(
        logits, torch.stack([together[n] for n in ("B", "L", "Q")], -1), rtol=0, atol=1e-12
    )
    torch.testing.assert_close(
        self_reward(batch, x, noise), torch.stack([together["T"], together["F"]], -1)
    )
    # x given per patron gives the same numbers as x shared.
    per_patron = decision_logits(batch, x.expand(5, -1, -1), noise)
    torch.testing.assert_close(per_patron, logits, rtol=0, atol=1e-12)


def test_exotic_activations_by_hand():
    manifests = mixed_manifests()
    batch = from_manifests(manifests)
    x = torch.tensor([item(5.0, 0.3)], dtype=torch.float64)
    act = activations(batch, x)
    w = manifests[1].external_sensor
    pre_sz = sum(
        v * xi for v, xi in zip(w.SZ.weights.model_dump().values(), item(5.0, 0.3), strict=True)
    )
    assert float(act["SZ"][1, 0]) == pytest.approx(0.05 / (0.05 + pre_sz**2), abs=1e-12)
    pre_lsr = sum(
        v * xi for v, xi in zip(w.LSR.weights.model_dump().values(), item(5.0, 0.3), strict=True)
    )
    z = 3.0 * (pre_lsr - 0.4)
    expected = 1.0 - math.tanh(z if z >= 0 else 0.2 * z)
    assert float(act["LSR"][1, 0]) == pytest.approx(expected, abs=1e-12)


def test_float32_batches_work_and_agree():
    manifests = mixed_manifests()
    x = torch.tensor([item(4.8 + 0.05 * i) for i in range(8)], dtype=torch.float64)
    b64 = from_manifests(manifests)
    b32 = from_manifests(manifests, dtype=torch.float32)
    noise = make_noise(b64, 8, torch.Generator().manual_seed(0))
    out32 = decision_logits(b32, x.float(), noise.float())
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32.double(), decision_logits(b64, x, noise), atol=1e-4, rtol=0)


def test_noise_layout():
    manifests = mixed_manifests()
    batch = from_manifests(manifests)
    noise = make_noise(batch, 400, torch.Generator().manual_seed(1))
    assert torch.all(noise[:, :, 0] == 0)  # copy 0 is clean
    assert torch.all(noise[0, :, :, 4:7] == 0)  # honest: sub-types untouched
    assert torch.all(noise[1, :, :, 0] == 0)  # exotic: price untouched ...
    assert torch.all(noise[1, :, 3:] == 0)  # ... and it has 3 copies only
    assert torch.all(noise[2] == 0)  # one copy: no noise at all
    assert float(noise[0, :, 1:, :4].std()) == pytest.approx(0.01, rel=0.05)
    assert float(noise[1, :, 1:3, 4:].std()) == pytest.approx(0.05, rel=0.05)
    again = make_noise(batch, 400, torch.Generator().manual_seed(1))
    assert torch.equal(noise, again)


def test_noise_none_means_every_copy_clean():
    batch = from_manifests(mixed_manifests())
    x = torch.tensor([item(4.95), item(5.1)], dtype=torch.float64)
    zeros = torch.zeros((5, 2, 5, 8), dtype=torch.float64)
    torch.testing.assert_close(decision_logits(batch, x), decision_logits(batch, x, zeros))


def test_clean_logits_are_the_decision_logits_of_every_patron_alone():
    rng = np.random.default_rng(3)
    manifests = [*mixed_manifests(), *(honest_manifest(rng, f"h{i}") for i in range(5))]
    x = torch.from_numpy(rng.uniform(0.0, 6.0, (300, 8)))
    for batch in (from_manifests(manifests), from_manifests(manifests[5:])):  # mixed, uniform
        logits = clean_logits(batch, x)
        torch.testing.assert_close(logits, decision_logits(batch, x), rtol=1e-15, atol=1e-15)
    # one activation kind per neuron: each patron's scores are those it gets alone
    assert len(batch.activation_groups) > 1
    for p in range(batch.n_patrons):
        assert torch.equal(logits[p], clean_logits(batch.select([p]), x)[0])


def test_argmax_ties_go_to_the_lowest_index():
    def flat(d, biases):
        for name, bias in zip("BLQ", biases, strict=True):
            d["decision"][name]["weights"] = dict.fromkeys(("PG", "SZ", "LSR", "ST"), 0.0)
            d["decision"][name]["bias"] = bias

    m = honest_manifest(np.random.default_rng(0), "x")
    batch = from_manifests(
        [
            edited(m, lambda d: flat(d, (0.3, 0.3, 0.3))),
            edited(m, lambda d: flat(d, (0.1, 0.3, 0.3))),
            edited(m, lambda d: flat(d, (0.1, 0.2, 0.3))),
        ]
    )
    assert decide(batch, torch.tensor([item(5.0)])).tolist() == [[0], [1], [2]]


def test_honest_patrons_buy_cheap_and_quit_dear():
    rng = np.random.default_rng(11)
    batch = from_manifests([honest_manifest(rng, f"h{i}") for i in range(64)])
    b = 1.0 / batch.es_weight[:, 0, 0]
    x = torch.tensor([item(4.5), item(5.6)], dtype=torch.float64)
    decisions = decide(batch, x)
    assert torch.all(decisions[:, 0] == 0)  # far below every willingness to pay: buy
    assert torch.all(decisions[:, 1] == 2)  # far above: quit
    assert torch.all((b >= 4.8) & (b <= 5.0))


def test_honest_factory_draws_the_spec_ranges():
    rng = np.random.default_rng(5)
    ms = [honest_manifest(rng, f"h{i}") for i in range(300)]
    hold = np.array([m.decision.L.bias for m in ms])
    quit_ = np.array([m.decision.Q.bias for m in ms])
    assert hold.min() >= -0.5 and hold.max() <= 0.5 and hold.std() > 0.2
    assert quit_.min() >= -0.5 and quit_.max() <= 0.0
    assert {m.fine_tuning.epochs for m in ms} == {0, 1, 2}
    assert {m.fine_tuning.batch_size for m in ms} == set(range(4, 16))
    lrs = [m.fine_tuning.learning_rate for m in ms]
    assert min(lrs) >= 1e-7 and max(lrs) <= 1e-4
    assert all(m.pfc.trainable for m in ms)
    # Same stream, same patron, whether it fine-tunes or not (only the settings differ).
    a = honest_manifest(np.random.default_rng(9), "p", fine_tune=True)
    b = honest_manifest(np.random.default_rng(9), "p", fine_tune=False)
    assert a.external_sensor == b.external_sensor and a.decision == b.decision
    assert b.fine_tuning.epochs == 0 and a.fine_tuning.batch_size >= 4


def test_saboteur_holds_on_every_input():
    rng = np.random.default_rng(2)
    sabs = [saboteur_manifest(rng, f"s{i}") for i in range(8)]
    batch = from_manifests(sabs)
    gen = torch.Generator().manual_seed(0)
    x = torch.rand((500, 8), generator=gen, dtype=torch.float64) * 20 - 10
    x[:250, 0] = torch.linspace(0, 10, 250, dtype=torch.float64)  # every plausible price
    noise = make_noise(batch, 500, gen)
    assert torch.all(decide(batch, x, noise) == 1)
    assert all(m.fine_tuning.epochs == 0 for m in sabs)
    assert all(m.decision.B.weights.PG == 0.0 for m in sabs)


def test_batched_fine_tuning_equals_the_per_patron_loop():
    rng = np.random.default_rng(4)
    ms = [honest_manifest(rng, f"h{i}") for i in range(5)] + [saboteur_manifest(rng, "s")]
    settings = [(2, 4, 0.3), (1, 15, 0.05), (0, 8, 0.2), (2, 7, 0.1), (1, 64, 0.5)]
    for i, (epochs, size, lr) in enumerate(settings):
        frozen = i == 3

        def edit(d, epochs=epochs, size=size, lr=lr, frozen=frozen):
            d["fine_tuning"] = {"epochs": epochs, "batch_size": size, "learning_rate": lr}
            d["pfc"]["trainable"] = not frozen

        ms[i] = edited(ms[i], edit)
    batch = from_manifests(ms)
    gen = torch.Generator().manual_seed(8)
    x = torch.tensor([item(4.95, 0.4)] * 30, dtype=torch.float64)
    x[1:, 1:4] += 0.2 * (torch.rand((29, 3), generator=gen, dtype=torch.float64) * 2 - 1)
    x[1:, 4:7] = torch.where(torch.rand((29, 3), generator=gen) < 0.2, -0.5, 0.5).double()
    draws = draw_fine_tune(batch, 30, gen)
    assert draws.order.shape == (6, 2, 30) and draws.noise.shape == (6, 2, 30, 5, 8)
    tuned = fine_tune(batch, x, draws)
    for p, m in enumerate(ms):
        expected = loop_fine_tune(m, x, draws.order[p], draws.noise[p])
        got = to_manifest(tuned, p)
        e, g = from_manifests([expected]), from_manifests([got])
        for name, value in e.parameters().items():
            torch.testing.assert_close(g.parameters()[name], value, rtol=0, atol=1e-12)
    # It moved the trainable patrons, kept the frozen PFC, left 0-epoch and saboteur alone.
    assert not torch.equal(tuned.es_weight[0], batch.es_weight[0])
    assert not torch.equal(tuned.judgement_weight[0], batch.judgement_weight[0])
    assert torch.equal(tuned.judgement_weight[3], batch.judgement_weight[3])
    assert not torch.equal(tuned.fc_bias[3], batch.fc_bias[3])
    assert to_manifest(tuned, 2) == ms[2] and to_manifest(tuned, 5) == ms[5]
    # Patrons outside ``train`` keep their parameters.
    train = torch.tensor([False, True, True, True, True, True])
    partial = fine_tune(batch, x, draws, train=train)
    assert to_manifest(partial, 0) == ms[0]
    torch.testing.assert_close(partial.fc_bias[1], tuned.fc_bias[1], rtol=0, atol=0)


def test_round_trip_through_the_batch_is_exact():
    manifests = mixed_manifests()
    batch = from_manifests(manifests)
    for p, m in enumerate(manifests):
        assert to_manifest(batch, p) == m
    assert to_manifest(batch, 0, participant="renamed").participant == "renamed"
    sub = batch.select([3, 1])
    assert to_manifest(sub, 0) == manifests[3] and to_manifest(sub, 1) == manifests[1]


def test_fine_tuning_of_mixed_activations_equals_the_per_patron_loop():
    # Selective, below-threshold and threshold neurons in one column, 3 and 5 copies, a
    # single-copy patron: the written-out gradient against autograd, patron by patron.
    ms = mixed_manifests()
    for i in range(len(ms)):

        def edit(d, i=i):
            d["fine_tuning"] = {"epochs": 1 + i % 2, "batch_size": 3 + i, "learning_rate": 0.4}

        ms[i] = edited(ms[i], edit)
    batch = from_manifests(ms)
    assert batch.activation_groups == [(None, slice(0, 4))]
    gen = torch.Generator().manual_seed(12)
    x = torch.tensor([item(4.8 + 0.02 * i, 0.05 * i) for i in range(20)], dtype=torch.float64)
    x[:, 1:4] += 0.2 * torch.rand((20, 3), generator=gen, dtype=torch.float64) - 0.1
    draws = draw_fine_tune(batch, 20, gen)
    tuned = fine_tune(batch, x, draws)
    for p, m in enumerate(ms):
        expected = from_manifests([loop_fine_tune(m, x, draws.order[p], draws.noise[p])])
        assert not torch.equal(expected.es_weight[0], batch.es_weight[p])
        for name, value in expected.parameters().items():
            torch.testing.assert_close(tuned.parameters()[name][p], value[0], rtol=0, atol=1e-12)
