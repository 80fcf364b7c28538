"""Worker pools: tasks run in worker processes at the configured (lower) CPU priority."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from pathlib import Path

import httpx
import pytest

from server.cli.launch import ServerProcess
from server.work.pool import WorkerContext, WorkerPool
from tests.support.live import submit_population
from tests.support.processes import descendants, process_name
from tests.support.server import ADMIN, ADMIN_TOKEN


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
        on_exit=lambda task_id, code, began: exits.append((task_id, code)),
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


@pytest.mark.slow  # 15 s; the default run keeps test_job_limits.py's time limits
def test_the_time_limit_counts_from_the_start_of_the_task_not_of_its_worker(tmp_path) -> None:
    """A fresh worker slower to start than the limit still runs its quick task to the end
    (done); a task longer than the limit is stopped at it (over, not done)."""
    ended: dict[int, bool] = {}
    timed_out: list[tuple[int, float]] = []
    context = WorkerContext(
        database_url="sqlite://", data_dir=str(tmp_path), progress_interval_s=1.0, torch_threads=1
    )
    pool = WorkerPool(
        name="test",
        task=SlowToStart(start_s=4.0),
        context=context,
        max_workers=1,
        on_exit=lambda task_id, code, began: None,
        tasks_per_process=1,  # as jobs: every task in a fresh worker
        timeout_s=2.0,
        on_timeout=lambda task_id, limit: timed_out.append((task_id, limit)),
        on_end=ended.__setitem__,
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
    assert ended == {1: True, 2: False}


@pytest.mark.parametrize("when", ["before_it_began", "while_it_ran"])
def test_a_worker_killed_says_whether_it_had_begun_its_task(tmp_path: Path, when: str) -> None:
    """A worker killed between the hand-out and its word that it began ran none of the task:
    its death is reported as such (the runner then runs the task again without counting the
    death against it, as it counts one while the task ran)."""
    exits: list[tuple[int, int | None, bool]] = []
    context = WorkerContext(
        database_url="sqlite://", data_dir=str(tmp_path), progress_interval_s=1.0, torch_threads=1
    )
    pool = WorkerPool(
        name="test",
        task=SlowToStart(start_s=60.0 if when == "before_it_began" else 0.0),
        context=context,
        max_workers=1,
        on_exit=lambda task_id, code, began: exits.append((task_id, code, began)),
    )
    pool.start()
    try:
        pool.submit(2)  # task 2 runs for a minute once begun
        deadline = time.monotonic() + 60  # the fork server imports torch first
        ran = tmp_path / "2"
        while time.monotonic() < deadline and (
            pool.pid(2) is None or (when == "while_it_ran" and not ran.exists())
        ):
            time.sleep(0.05)
        pid = pool.pid(2)
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        while not exits and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        pool.shutdown()
    assert exits == [(2, -signal.SIGKILL, when == "while_it_ran")]
    assert ran.exists() is (when == "while_it_ran")


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
        on_exit=lambda task_id, code, began: None,
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


def _niceness(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[16])


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
@pytest.mark.slow  # 13 s
def test_step_workers_run_at_the_api_priority_and_job_workers_below_it(tmp_path: Path) -> None:
    """``SRD_WORKER_NICE`` lowers the experiments' priority only: an auction's steps are part of
    serving (a round closes when its step has run). The server runs from a folder holding
    another ``server`` package: no process of it imports that one (the fork server, a
    ``python -c``, once put the current folder first on its path)."""
    elsewhere = tmp_path / "elsewhere"
    (elsewhere / "server").mkdir(parents=True)
    marker = elsewhere / "imported"
    (elsewhere / "server" / "__init__.py").write_text(
        f"open({str(marker)!r}, 'w').close()\nraise ImportError('another server')\n"
    )
    with ServerProcess(
        database_url=f"sqlite:///{tmp_path / 'srd.db'}",
        data_dir=tmp_path,
        admin_token=ADMIN_TOKEN,
        extra_env={"SRD_WORKER_NICE": "7"},
        cwd=elsewhere,
    ) as server:
        assert server.process is not None
        api = server.process.pid
        with httpx.Client(base_url=server.url, timeout=30) as client:
            submit_population(client)
            auction = client.post("/auctions", json={"n_fish": 3, "seed": 0}, headers=ADMIN)
            job = client.post("/jobs", json={"kind": "fish", "params": {}}, headers=ADMIN)
            assert (auction.status_code, job.status_code) == (201, 202), (auction.text, job.text)
            api_nice = _niceness(api)
            expected = {"srd-auction": api_nice, "srd-job": min(api_nice + 7, 19)}
            seen: dict[str, int] = {}
            deadline = time.monotonic() + 120  # the fork server imports torch first
            # A worker names itself first thing and lowers its priority a moment later: read
            # until both kinds show the expected niceness (or the time is up).
            while seen != expected and time.monotonic() < deadline:
                for pid in descendants(api)[1:]:
                    name = process_name(pid) or ""
                    for kind in ("srd-auction", "srd-job"):
                        if name.startswith(kind):
                            with contextlib.suppress(OSError):
                                seen[kind] = _niceness(pid)
                time.sleep(0.02)
            auction_id = auction.json()["auction_id"]
            while time.monotonic() < deadline:
                state = client.get(f"/auctions/{auction_id}").json()
                if state["status"] not in ("pending", "running"):
                    break
                time.sleep(0.1)
    assert seen == expected
    assert state["status"] == "finished", state["error"]
    assert not marker.exists()  # no process of the server imported the folder's package
