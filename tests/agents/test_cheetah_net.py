"""HalfCheetahSRD neuron by neuron, against float64 formulas of the reference's neurons."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from agents.cheetah_net import (
    ACTUATORS,
    FEATURES,
    STABLE_POSE_X,
    STABLE_POSE_Z,
    WEIGHT_NOISE,
    HalfCheetahSRD,
    StablePoseNeuron,
    noisy_fc_weight,
    nominal_fc_weight,
)

REST = torch.tensor([STABLE_POSE_X + STABLE_POSE_Z], dtype=torch.float32)


def reference_actions(u, weight, bias, backswing, inhibitor):
    """a = tanh(2 (W LeakyReLU(h − inhibitor) + b)) in float64."""
    u = np.asarray(u, dtype=np.float64)
    dx = ((u[:6] - np.array(STABLE_POSE_X)) ** 2).sum()
    dz = ((u[6:] - np.array(STABLE_POSE_Z)) ** 2).sum()
    xs, zs = 1e-4 / (1e-4 + dx**2), 1e-4 / (1e-4 + dz**2)
    h = np.array([xs, zs, 1 - xs, 1 - zs, backswing * u[6]]) - inhibitor
    h = np.where(h >= 0, h, 0.01 * h)
    return np.tanh(2 * (np.asarray(weight, dtype=np.float64) @ h + np.asarray(bias)))


def test_stable_pose_neuron_is_one_at_rest_and_half_at_ten_centimetres():
    neuron = StablePoseNeuron(torch.zeros(3, 6, dtype=torch.float64))
    u = torch.zeros(3, 6, dtype=torch.float64)
    u[1, 0] = 0.1  # ‖u − p‖ = 0.1 m = ε^¼
    u[2, :] = 0.1  # ‖u − p‖² = 0.06
    out = neuron(u)
    assert out[0].item() == 1.0
    assert out[1].item() == pytest.approx(0.5, abs=1e-12)
    assert out[2].item() == pytest.approx(1e-4 / (1e-4 + 0.06**2), rel=1e-12)


def test_features_at_the_resting_pose():
    net = HalfCheetahSRD(torch.tensor([3.0]))
    h = net.features(REST)[0]
    assert h[:2].tolist() == [1.0, 1.0]
    assert h[2:4].tolist() == [0.0, 0.0]
    assert h[4].item() == pytest.approx(3.0 * STABLE_POSE_Z[0], rel=1e-6)  # BS = b · z_bthigh


def test_designed_weights_swing_the_front_thigh_at_rest():
    net = HalfCheetahSRD(torch.tensor([0.0]))
    actions = net(REST, torch.zeros(1))[0]
    assert actions[ACTUATORS.index("ft")].item() == pytest.approx(math.tanh(-4.0), abs=1e-6)
    others = [a for i, a in enumerate(actions.tolist()) if i != ACTUATORS.index("ft")]
    assert max(abs(a) for a in others) < 1e-6
    weight = nominal_fc_weight()
    assert weight[ACTUATORS.index("bt")].tolist() == pytest.approx([0, 0, -0.2, -0.2, 1])
    assert nominal_fc_weight(design_offset=True)[1, 1].item() == pytest.approx(1e-4)


def test_inhibitor_two_silences_every_actuator():
    gen = torch.Generator().manual_seed(3)
    u = REST + 0.2 * torch.randn(64, 12, generator=gen)
    u[:, 6] = torch.linspace(-0.3, 0.3, 64)  # pitch within ±35°: BS = 5 · z stays below 2
    net = HalfCheetahSRD(torch.full((64,), 5.0), fc_weight=noisy_fc_weight([gen] * 64))
    free = net(u, torch.zeros(64))
    stopped = net(u, torch.full((64,), 2.0))
    assert free.abs().max() > 0.9
    assert stopped.abs().max() < 0.1


@pytest.mark.parametrize("inhibitor", [0.0, 2.0])
def test_forward_matches_the_float64_formula(inhibitor):
    gen = torch.Generator().manual_seed(11)
    n = 16
    u = REST + 0.15 * torch.randn(n, 12, generator=gen)
    backswing = torch.linspace(1, 5, n)
    weight = noisy_fc_weight([gen] * n)
    net = HalfCheetahSRD(backswing, fc_weight=weight)
    with torch.no_grad():
        net.fc_bias.copy_(0.05 * torch.randn(n, 6, generator=gen))
        actions = net(u, torch.full((n,), inhibitor)).double().numpy()
    for i in range(n):
        expected = reference_actions(
            u[i], weight[i], net.fc_bias[i].detach().double(), backswing[i].item(), inhibitor
        )
        np.testing.assert_allclose(actions[i], expected, atol=2e-6)


def test_pfc_verdicts_follow_the_spec_formulas():
    net = HalfCheetahSRD(torch.ones(4))
    actions = torch.tensor([[0.0] * 6, [0.5] * 6, [1.0] * 6, [0.2] * 6])
    for inhibitor in (0.0, 2.0):
        z = net.judge(actions, torch.full((4,), inhibitor)).double()
        ac = (actions.double() ** 2).mean(dim=1)
        g0, g1 = torch.tanh(4 * (ac - inhibitor)), torch.tanh(4 * (ac + inhibitor))
        torch.testing.assert_close(z[:, 0], g0 + 0.01 * g1, atol=1e-6, rtol=0)
        torch.testing.assert_close(z[:, 1], -0.01 * g0 + g1 - 0.2, atol=1e-6, rtol=0)
        verdict_true = (z[:, 0] > z[:, 1]).tolist()
        assert verdict_true == [inhibitor == 0.0] * 4  # T without the inhibitor, F with it


def test_srd_step_is_per_trial_sgd_and_skips_trials_without_srd():
    gen = torch.Generator().manual_seed(5)
    n = 3
    u = REST + 0.1 * torch.randn(n, 12, generator=gen)
    inhibitor = torch.tensor([0.0, 0.0, 2.0])
    weight = noisy_fc_weight([gen] * n)
    lr = torch.tensor([0.1, 0.1, 0.05])
    net = HalfCheetahSRD(torch.tensor([3.0, 4.0, 5.0]), fc_weight=weight)
    before = [p.detach().clone() for p in net.parameters()]
    net.act(u, inhibitor, srd=torch.tensor([True, False, True]), lr=lr)
    for p, old in zip(net.parameters(), before, strict=True):
        assert torch.equal(p[1], old[1])  # SRD off: untouched
    for trial in (0, 2):  # same step as a one-trial network with torch's own SGD
        single = HalfCheetahSRD(torch.tensor([3.0 + trial]), fc_weight=weight[trial : trial + 1])
        optimiser = torch.optim.SGD(single.parameters(), lr=lr[trial].item())
        actions = single(u[trial : trial + 1], inhibitor[trial : trial + 1])
        z = single.judge(actions, inhibitor[trial : trial + 1])
        torch.nn.functional.cross_entropy(z, z.detach().argmax(dim=1)).backward()
        optimiser.step()
        for p, q in zip(net.parameters(), single.parameters(), strict=True):
            torch.testing.assert_close(p[trial], q[0].detach(), atol=1e-7, rtol=1e-6)
    changed = max(
        (p[0] - old[0]).abs().max().item() for p, old in zip(net.parameters(), before, strict=True)
    )
    assert changed > 1e-4


def test_no_srd_returns_no_logits_and_keeps_weights():
    net = HalfCheetahSRD(torch.ones(2))
    before = [p.detach().clone() for p in net.parameters()]
    actions, logits = net.act(REST.repeat(2, 1), torch.zeros(2))
    assert logits is None and actions.shape == (2, 6)
    assert all(torch.equal(p, q) for p, q in zip(net.parameters(), before, strict=True))


def test_noise_is_seeded_and_one_hundredth():
    draws = [noisy_fc_weight([torch.Generator().manual_seed(s)]) for s in (1, 1, 2)]
    assert torch.equal(draws[0], draws[1]) and not torch.equal(draws[0], draws[2])
    many = noisy_fc_weight([torch.Generator().manual_seed(s) for s in range(200)])
    noise = many - nominal_fc_weight()
    assert noise.std().item() == pytest.approx(WEIGHT_NOISE, rel=0.05)


def test_every_weight_has_a_name():
    net = HalfCheetahSRD(torch.tensor([4.0]))
    names = net.named_weights(0)
    n_numbers = sum(p[0].numel() for p in net.parameters()) + 1  # + the backswing gain
    assert len(names) == n_numbers == 12 + 30 + 6 + 4 + 4 + 2 + 1
    assert names["fc.ft.xS"] == -1.0 and names["fc.bt.BS"] == 1.0
    assert names["pfc.F.bias"] == pytest.approx(-0.2)
    assert names["xS.p.bthigh"] == pytest.approx(STABLE_POSE_X[0])
    assert {n.split(".")[2] for n in names if n.startswith("fc.")} == {*FEATURES, "bias"}


def test_wrong_weight_shape_is_refused():
    with pytest.raises(ValueError, match=r"\(2, 6, 5\)"):
        HalfCheetahSRD(torch.ones(2), fc_weight=torch.zeros(2, 6, 4))
