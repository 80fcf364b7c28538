"""The SRD vocabulary: activations with a meaning, and the self-reward loss.

* selective activation  S(x; ε) = ε / (ε + x²): 1 exactly when x = 0, a "this and only this"
  detector (food here, stable pose, tile of a known colour).
* threshold activation  T(x; a, c, ns) = tanh(leaky_relu(a·(x − c), ns)): lights up once x
  exceeds the threshold c, with sharpness a; below c it stays near 0 (slope ns).
* below-threshold activation  BT(x; a, c, ns) = tanh(−leaky_relu(a·(x − c), ns)) + 1: the
  mirror image, ≈1 well below c and falling to 0 above it.
* self-reward loss  CEL(z, argmax z): the PFC's logits z = [T, F] are their own label.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from agents.neuron_defaults import (
    NEGATIVE_SLOPE,
    SELECTIVE_EPSILON,
    THRESHOLD_CENTRE,
    THRESHOLD_SHARPNESS,
)

__all__ = [
    "NEGATIVE_SLOPE",
    "SELECTIVE_EPSILON",
    "THRESHOLD_CENTRE",
    "THRESHOLD_SHARPNESS",
    "below_threshold",
    "selective",
    "self_reward_loss",
    "threshold",
]


def selective(x: Tensor, epsilon: float | Tensor = SELECTIVE_EPSILON) -> Tensor:
    """S(x; ε) = ε / (ε + x²), in (0, 1], equal to 1 at x = 0 and 0.5 at |x| = √ε."""
    return epsilon / (epsilon + x * x)


def threshold(
    x: Tensor,
    a: float | Tensor = THRESHOLD_SHARPNESS,
    c: float | Tensor = THRESHOLD_CENTRE,
    negative_slope: float | Tensor = NEGATIVE_SLOPE,
) -> Tensor:
    """T(x; a, c, ns) = tanh(leaky_relu(a·(x − c), ns)).

    ``negative_slope`` may be a tensor (one slope per neuron), unlike ``F.leaky_relu``.
    """
    return torch.tanh(_leaky_relu(a * (x - c), negative_slope))


def below_threshold(
    x: Tensor,
    a: float | Tensor = THRESHOLD_SHARPNESS,
    c: float | Tensor = THRESHOLD_CENTRE,
    negative_slope: float | Tensor = NEGATIVE_SLOPE,
) -> Tensor:
    """BT(x; a, c, ns) = tanh(−leaky_relu(a·(x − c), ns)) + 1: ≈1 below c, → 0 above it."""
    return torch.tanh(-_leaky_relu(a * (x - c), negative_slope)) + 1.0


def _leaky_relu(z: Tensor, negative_slope: float | Tensor) -> Tensor:
    """leaky_relu with a scalar or per-element slope."""
    if isinstance(negative_slope, Tensor):
        return torch.where(z >= 0, z, negative_slope * z)
    return F.leaky_relu(z, float(negative_slope))


def self_reward_loss(z: Tensor, reduction: str = "mean") -> Tensor:
    """CrossEntropy(z, argmax z): the SRD loss, with the PFC's own verdict as the label.

    ``z`` has shape (..., n_classes); the label is detached (ties → lowest index).
    """
    flat = z.reshape(-1, z.shape[-1])
    label = flat.detach().argmax(dim=-1)
    loss = F.cross_entropy(flat, label, reduction="none").reshape(z.shape[:-1])
    if reduction == "none":
        return loss
    if reduction == "sum":
        return loss.sum()
    return loss.mean()
