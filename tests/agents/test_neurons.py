"""The SRD activations and the self-reward loss against hand-computed numbers."""

from __future__ import annotations

import math

import pytest
import torch

from agents.neurons import below_threshold, selective, self_reward_loss, threshold


def t(*values: float) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


def test_selective_is_one_at_zero_and_half_at_sqrt_epsilon():
    out = selective(t(0.0, 0.01, -0.01, 0.1), epsilon=1e-4)
    assert out.tolist() == pytest.approx([1.0, 0.5, 0.5, 1e-4 / (1e-4 + 0.01)], abs=1e-12)


def test_selective_default_epsilon_is_the_reference_1e4():
    # ST of the FSN at the prototype row: pre-activation 0.0084 → 0.586 (the reference's table).
    assert float(selective(t(0.0084))) == pytest.approx(1e-4 / (1e-4 + 0.0084**2), abs=1e-12)
    assert float(selective(t(0.0084))) == pytest.approx(0.586, abs=1e-3)


def test_threshold_values():
    # a = 20, c = 1: at x = 1.05 the argument is 1.0; below c the slope is 0.01.
    out = threshold(t(1.05, 1.0, 0.9), a=20.0, c=1.0, negative_slope=0.01)
    assert out.tolist() == pytest.approx([math.tanh(1.0), 0.0, math.tanh(-0.01 * 2.0)], abs=1e-12)


def test_threshold_with_a_tensor_slope_matches_the_scalar_slope():
    x = torch.linspace(-2, 2, 41, dtype=torch.float64)
    scalar = threshold(x, a=5.0, c=1.0, negative_slope=0.8)
    per_neuron = threshold(x, a=5.0, c=1.0, negative_slope=torch.full_like(x, 0.8))
    torch.testing.assert_close(scalar, per_neuron, rtol=0, atol=1e-15)
    assert float(threshold(t(0.8), a=5.0, c=1.0, negative_slope=0.8)) == pytest.approx(
        math.tanh(-0.8), abs=1e-12
    )


def test_below_threshold_mirrors_threshold():
    x = torch.linspace(-1, 3, 17, dtype=torch.float64)
    below = below_threshold(x, a=5.0, c=1.0, negative_slope=0.01)
    torch.testing.assert_close(below, 1.0 - threshold(x, a=5.0, c=1.0), rtol=0, atol=1e-15)
    assert float(below_threshold(t(5.0), a=5.0, c=1.0)) == pytest.approx(0.0, abs=1e-12)
    assert float(below_threshold(t(1.0), a=5.0, c=1.0)) == 1.0
    slope = torch.full_like(x, 0.01)
    torch.testing.assert_close(below, below_threshold(x, 5.0, 1.0, slope), rtol=0, atol=1e-15)


def test_self_reward_loss_is_cross_entropy_against_its_own_argmax():
    z = t(2.0, 0.0, 0.0, 1.0, 0.5, 0.5).reshape(3, 2)
    losses = self_reward_loss(z, reduction="none")
    expected = [math.log1p(math.exp(-2.0)), math.log1p(math.exp(-1.0)), math.log(2.0)]
    assert losses.tolist() == pytest.approx(expected, abs=1e-12)
    assert float(self_reward_loss(z)) == pytest.approx(sum(expected) / 3, abs=1e-12)
    assert float(self_reward_loss(z, reduction="sum")) == pytest.approx(sum(expected), abs=1e-12)


def test_self_reward_loss_keeps_leading_shape_and_detaches_the_label():
    z = torch.tensor([[[0.3, 0.1], [0.0, 0.4]]], dtype=torch.float64, requires_grad=True)
    loss = self_reward_loss(z, reduction="none")
    assert loss.shape == (1, 2)
    loss.sum().backward()
    # d CE / d z = softmax(z) − onehot(argmax z): the label is a constant.
    soft = torch.softmax(z.detach(), dim=-1)
    onehot = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]], dtype=torch.float64)
    torch.testing.assert_close(z.grad, soft - onehot)
