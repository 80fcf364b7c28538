"""Rules of the settings: augmentation noise and fine-tuning within sane bounds."""

from __future__ import annotations

import numpy as np

from agents.manifest import INPUTS
from screener import limits
from screener.findings import Checks, check
from screener.rules.numbers import Numbers


def setting_checks(n: Numbers) -> list[Checks]:
    """Augmentation and fine-tuning settings within sane bounds."""
    std, lr, epochs = n.noise_std, n.learning_rate, n.epochs
    steps = epochs * np.ceil(limits.MARKET.n_rows / n.batch_size)
    subtype_cols = [INPUTS.index(name) for name in limits.NOISELESS_SUBTYPES]
    jittered = n.noise_mask[:, subtype_cols].max(axis=1) > 0
    return [
        check(
            "augmentation-noise",
            "PG",
            std > limits.NOISE_STD_LIMIT,
            lambda p: (
                f"augmentation noise σ = {std[p]:.3g} jitters the price PG reads by about "
                f"±{std[p]:.2f} (at most {limits.NOISE_STD_LIMIT:g}): its votes near its price "
                "become random"
            ),
        ),
        check(
            "augmentation-subtypes",
            "ST",
            (std > 0) & jittered,
            lambda p: (
                "augmentation jitters the sub-type flags: they are discrete, and noise "
                f"σ = {std[p]:.3g} blurs the selective ST neuron's peak"
            ),
        ),
        check(
            "fine-tuning",
            "T",
            (lr > limits.LEARNING_RATE_LIMIT) | (epochs > limits.EPOCHS_LIMIT),
            lambda p: (
                f"fine-tuning with learning rate {lr[p]:.3g} for {int(epochs[p])} epochs "
                f"(at most {limits.LEARNING_RATE_LIMIT:g} and {limits.EPOCHS_LIMIT}) would push "
                "the model towards the PFC verdict T/F faster than re-screening can follow"
            ),
        ),
        check(
            "fine-tuning-steps",
            "T",
            steps > limits.STEPS_LIMIT,
            lambda p: (
                f"fine-tuning takes {int(steps[p])} SGD steps a round ({int(epochs[p])} epochs "
                f"at batch size {int(n.batch_size[p])} over {limits.MARKET.n_rows} item rows; "
                f"at most {limits.STEPS_LIMIT}): every auction it enters, and its screening, "
                "would pay for them"
            ),
        ),
    ]
