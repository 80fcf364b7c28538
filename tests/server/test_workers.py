"""Worker pools: tasks run in worker processes at the configured (lower) CPU priority."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from server.work.pool import WorkerContext, WorkerPool


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


class SlowToStart:
    """A task whose worker takes ``start_s`` to come up (it sleeps while the child unpickles
    it, as a fresh worker imports torch under load); task 2 then runs for a minute."""

    def __init__(self, start_s: float) -> None:
        self.start_s = start_s

    def __setstate__(self, state: dict[str, float]) -> None:
        self.__dict__.update(state)
        time.sleep(self.start_s)

    def __call__(self, context: WorkerContext, task_id: int) -> None:
        Path(context.data_dir, str(task_id)).write_text("ran")
        if task_id == 2:
            time.sleep(60)


def test_the_time_limit_counts_from_the_start_of_the_task_not_of_its_worker(tmp_path) -> None:
    """A fresh worker slower to start than the limit still runs its quick task to the end;
    a task longer than the limit is stopped at it."""
    ended: list[int] = []
    timed_out: list[tuple[int, float]] = []
    context = WorkerContext(
        database_url="sqlite://", data_dir=str(tmp_path), progress_interval_s=1.0, torch_threads=1
    )
    pool = WorkerPool(
        name="test",
        task=SlowToStart(start_s=4.0),
        context=context,
        max_workers=1,
        on_exit=lambda task_id, code: None,
        tasks_per_process=1,  # as jobs: every task in a fresh worker
        timeout_s=2.0,
        on_timeout=lambda task_id, limit: timed_out.append((task_id, limit)),
        on_end=ended.append,
    )
    pool.start()
    try:
        for task_id in (1, 2):
            pool.submit(task_id)
            deadline = time.monotonic() + 120  # start-up, torch imports on a loaded machine
            while task_id not in ended and time.monotonic() < deadline:
                time.sleep(0.1)
            assert task_id in ended
            assert (tmp_path / str(task_id)).read_text() == "ran"
    finally:
        pool.shutdown()
    assert timed_out == [(2, 2.0)]


def record_environment(context: WorkerContext, task_id: int) -> None:
    """A task: write the worker's ``SRD_TEST_MARK`` to ``<data_dir>/<task_id>``."""
    Path(context.data_dir, str(task_id)).write_text(os.environ.get("SRD_TEST_MARK", "unset"))


def run_one(pool: WorkerPool, task_id: int, folder: Path) -> str:
    pool.submit(task_id)
    result = folder / str(task_id)
    deadline = time.monotonic() + 60  # the fork server imports torch first
    while not (result.exists() and result.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    return result.read_text()


def test_a_worker_sees_the_environment_of_its_start_not_of_the_first_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Workers fork from a long-lived server: one started after the API's environment changed
    (a token set, say) sees the change, as a freshly spawned process would."""
    monkeypatch.setenv("SRD_TEST_MARK", "before")
    context = WorkerContext(
        database_url="sqlite://", data_dir=str(tmp_path), progress_interval_s=1.0, torch_threads=1
    )
    pool = WorkerPool(
        name="test",
        task=record_environment,
        context=context,
        max_workers=1,
        on_exit=lambda task_id, code: None,
        tasks_per_process=1,  # a new worker per task
    )
    pool.start()
    try:
        assert run_one(pool, 1, tmp_path) == "before"
        monkeypatch.setenv("SRD_TEST_MARK", "after")
        run_one(pool, 2, tmp_path)  # on the spare worker, which may have started before that
        assert run_one(pool, 3, tmp_path) == "after"  # a worker started after task 2 ended
    finally:
        pool.shutdown()
