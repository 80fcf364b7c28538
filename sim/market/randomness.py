"""Every random stream of an auction, all derived from its seed: its own generators
(``AuctionRandom``) and the seeds of its fine-tuning rounds (``round_seeds``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from agents.fine_tuning import derive_seeds

FINE_TUNE_STREAM, AUGMENTATION_STREAM = 1, 2
"""Children of an iteration's seed: the round's shuffle seed and its augmentation seed."""


@dataclass
class AuctionRandom:
    """An auction's generators: numpy for the rows and price raises; torch ``decisive`` for
    row 0's augmentation noise; torch ``rows`` for rows 1.. (fine-tuning rounds draw from
    per-patron generators instead, see ``round_seeds``)."""

    numpy: np.random.Generator
    decisive: torch.Generator
    rows: torch.Generator

    @classmethod
    def from_seed(cls, seed: int) -> AuctionRandom:
        numpy_seq, decisive_seq, rows_seq = np.random.SeedSequence(seed).spawn(3)

        def torch_generator(seq: np.random.SeedSequence) -> torch.Generator:
            return torch.Generator().manual_seed(int(seq.generate_state(1, np.uint64)[0]))

        return cls(
            np.random.default_rng(numpy_seq),
            torch_generator(decisive_seq),
            torch_generator(rows_seq),
        )

    def copy(self) -> AuctionRandom:
        """Independent generators in the same state."""
        numpy = np.random.Generator(type(self.numpy.bit_generator)())
        numpy.bit_generator.state = self.numpy.bit_generator.state
        return AuctionRandom(numpy, self.decisive.clone_state(), self.rows.clone_state())

    def state(self) -> dict[str, Any]:
        return {
            "numpy": self.numpy.bit_generator.state,
            "decisive": self.decisive.get_state(),
            "rows": self.rows.get_state(),
        }

    def load(self, state: dict[str, Any]) -> None:
        self.numpy.bit_generator.state = state["numpy"]
        self.decisive.set_state(state["decisive"])
        self.rows.set_state(state["rows"])


def round_seeds(seed: int, iteration: int) -> tuple[int, int]:
    """(fine_tune_seed, augmentation_seed) of the fine-tuning round after ``iteration`` of the
    auction seeded ``seed``."""
    base = derive_seeds(seed, iteration)
    shuffle, noise = derive_seeds(base, [FINE_TUNE_STREAM, AUGMENTATION_STREAM]).tolist()
    return int(shuffle), int(noise)
