"""``Market``: one auction, played iteration by iteration over a one-auction ``MarketBatch``."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

from agents.manifest import Manifest
from sim.market import checkpoint
from sim.market.config import MarketConfig
from sim.market.engine import MarketBatch, Rescreen, RescreenBatch
from sim.market.records import IterationRecord
from sim.market.rounds import FineTuneRound


class Market:
    """One auction (see ``sim.market``); ``rescreen`` re-checks fine-tuned patrons. Its records
    explain every vote (``IterationRecord.explanations``): one auction is what the server plays
    and shows, and one more row-0 pass costs little next to the iteration."""

    def __init__(
        self,
        manifests: Sequence[Manifest],
        config: MarketConfig,
        *,
        rescreen: Rescreen | None = None,
        rescreen_batch: RescreenBatch | None = None,
    ) -> None:
        self.config = config
        self._engine = MarketBatch(
            [(manifests, config)], rescreen=[rescreen], rescreen_batch=rescreen_batch, explain=True
        )

    @property
    def finished(self) -> bool:
        return bool(self._engine.finished[0])

    @property
    def iteration(self) -> int:
        """Iterations done so far."""
        return int(self._engine.iteration[0])

    @property
    def price(self) -> float:
        return float(self._engine.price[0])

    @property
    def n_available(self) -> int:
        return int(self._engine.n_available[0])

    @property
    def stop_reason(self) -> str | None:
        return self._engine.stop_reason[0]

    def step(self) -> IterationRecord:
        """One iteration; raises RuntimeError once the auction has finished."""
        if self.finished:
            raise RuntimeError("the auction has finished")
        record = self._engine.step()[0]
        assert record is not None
        return record

    def run(self) -> Iterator[IterationRecord]:
        """Iterate to the end, yielding each iteration's record."""
        while not self.finished:
            yield self.step()

    def checkpoint(self) -> bytes:
        """The state after the last iteration, as bytes (``restore`` continues from it)."""
        return checkpoint.dump(self._engine)

    @classmethod
    def restore(
        cls,
        manifests: Sequence[Manifest],
        config: MarketConfig,
        blob: bytes,
        *,
        rescreen: Rescreen | None = None,
        rescreen_batch: RescreenBatch | None = None,
    ) -> Market:
        """The auction of ``manifests`` and ``config`` as it was at ``checkpoint()``."""
        market = cls(manifests, config, rescreen=rescreen, rescreen_batch=rescreen_batch)
        checkpoint.load(market._engine, blob)
        return market

    def current_manifests(self) -> list[Manifest]:
        """The patrons with their current (possibly fine-tuned) parameters."""
        return self._engine.manifests(0)

    def current_manifest(self, position: int) -> Manifest:
        """Patron ``position`` with its current (possibly fine-tuned) parameters."""
        return self._engine.manifest(0, position)

    @property
    def pending_round(self) -> FineTuneRound | None:
        """The remote fine-tuning round awaiting ``apply_round`` (``step`` refuses until then)."""
        return self._engine.pending_round(0)

    def apply_round(self, updates: Mapping[int, Manifest]) -> None:
        """Close the pending round with the patrons' fine-tuned manifests by position (see
        ``MarketBatch.apply_round``)."""
        self._engine.apply_round(0, updates)
