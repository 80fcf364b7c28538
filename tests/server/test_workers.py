"""Worker pools: tasks run in spawned processes at the configured (lower) CPU priority."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from server.workers import WorkerContext, WorkerPool


def record_niceness(context: WorkerContext, task_id: int) -> None:
    """A task: write this process's niceness to ``<data_dir>/<task_id>``."""
    Path(context.data_dir, str(task_id)).write_text(str(os.nice(0)))


@pytest.mark.skipif(not hasattr(os, "nice"), reason="POSIX niceness only")
@pytest.mark.parametrize("nice", [0, 7])
def test_workers_run_at_the_configured_niceness(tmp_path: Path, nice: int) -> None:
    exits: list[tuple[int, int | None]] = []
    context = WorkerContext(
        database_url="sqlite://",
        data_dir=str(tmp_path),
        progress_interval_s=1.0,
        torch_threads=1,
        nice=nice,
    )
    pool = WorkerPool(
        name="test",
        task=record_niceness,
        context=context,
        max_workers=1,
        on_exit=lambda task_id, code: exits.append((task_id, code)),
    )
    pool.start()
    try:
        pool.submit(1)
        result = tmp_path / "1"
        deadline = time.monotonic() + 60  # the first worker imports torch
        while not (result.exists() and result.read_text()) and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        pool.shutdown()
    assert result.exists(), f"the task did not run; exits: {exits}"
    assert int(result.read_text()) == min(os.nice(0) + nice, 19)
