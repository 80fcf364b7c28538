"""Bounded, loud jobs: a job over its time limit is stopped and failed saying so; a job that
fails for a real cause carries that cause (type and message), stored by its worker."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import subprocess
import threading
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

import server
from server.app import create_app
from sim.experiment import config_fields
from studies.registry import KINDS
from tests.support.databases import postgres_admin_url, throwaway_postgres
from tests.support.factories import honest, unique
from tests.support.processes import refuse_starts
from tests.support.server import ADMIN, make_settings, wait_for

ENDED = {"succeeded", "failed", "cancelled"}


def run_to_end(client: TestClient, body: dict[str, Any], timeout_s: float = 120) -> dict[str, Any]:
    created = client.post("/jobs", json=body, headers=ADMIN)
    assert created.status_code == 202, created.text
    job_id = created.json()["job_id"]
    return wait_for(
        lambda: client.get(f"/jobs/{job_id}").json(), lambda s: s["status"] in ENDED, timeout_s
    )


@contextlib.contextmanager
def limited_app(tmp_path: Path, job_timeout_s: float) -> Iterator[tuple[TestClient, Any]]:
    """The app with one job worker, at niceness 0 (a niced worker gets a tenth of a core beside
    busy tests, and a quick job, mostly its plot's imports, then took over 10 s), and the time
    limit ``job_timeout_s``; a worker's start-up is not counted (the limit runs from when it
    begins the job)."""
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    update = {"job_timeout_s": job_timeout_s, "job_workers": 1, "worker_nice": 0}
    settings = settings.model_copy(update=update)
    with TestClient(create_app(settings)) as client:
        yield client, settings


@pytest.fixture
def limited(tmp_path: Path) -> Iterator[tuple[TestClient, Any]]:
    # 10 s: the quick job (fish, 10 steps and its plot: about 1 s on an idle machine) succeeds
    # even on a loaded machine
    with limited_app(tmp_path, 10.0) as app:
        yield app


def test_a_job_over_its_time_limit_is_stopped_and_failed(tmp_path: Path) -> None:
    """...and its folder removed with what it had written. A 5 s limit: the job stopped keeps
    a core busy until then, and the test writes into its folder before that."""
    with limited_app(tmp_path, 5.0) as (client, settings):
        body = {"kind": "fish", "params": {"steps": 1_000_000}}  # minutes
        job_id = client.post("/jobs", json=body, headers=ADMIN).json()["job_id"]
        folder = settings.data_dir / "jobs" / str(job_id)
        wait_for(lambda: {"made": folder.is_dir()}, lambda s: s["made"], 60)
        (folder / "energy.csv").write_text("step\n1\n")  # as a run writes files before its end
        job = wait_for(
            lambda: client.get(f"/jobs/{job_id}").json(), lambda s: s["status"] in ENDED, 120
        )
        assert job["status"] == "failed"
        assert job["message"] == "failed: stopped at the job time limit of 5 s (SRD_JOB_TIMEOUT_S)"
        assert "time limit of 5 s (SRD_JOB_TIMEOUT_S)" in job["error"]
        assert job["artifacts"] == []
        wait_for(lambda: {"kept": folder.exists()}, lambda s: not s["kept"], 15)  # once it is gone
        quick = run_to_end(client, {"kind": "fish", "params": {"steps": 10}})
        # The pool carries on: the next job runs, for a time limit of its own (about 1 s on an idle
        # machine; one loaded by more test processes than cores has made it run past 10 s).
        if quick["status"] != "succeeded":
            assert "time limit of 5 s" in quick["error"], quick["error"]
            ran = datetime.fromisoformat(quick["finished_at"]) - datetime.fromisoformat(
                quick["started_at"]
            )
            # its own 5 s (less the claim's delay), not what was left of another's
            assert ran.total_seconds() >= 4, ran


def test_a_real_failure_is_stored_with_its_cause(limited) -> None:
    client, settings = limited
    jobs = settings.data_dir / "jobs"
    jobs.parent.mkdir(parents=True, exist_ok=True)
    jobs.write_text("a file where the job folders should be")
    job = run_to_end(client, {"kind": "fish", "params": {"steps": 10}})
    assert job["status"] == "failed"
    assert job["message"].startswith(("failed: FileExistsError", "failed: NotADirectoryError"))
    assert "Traceback" in job["error"] and str(jobs) in job["error"]
    # its frames name the project's files, not where the server is installed (the field is
    # public)
    assert 'File "server/jobs/worker.py"' in job["error"]
    assert str(Path(server.__file__).resolve().parents[1]) not in job["error"]


@pytest.mark.parametrize(
    ("body", "option"),
    [
        ({"kind": "fish", "params": {"steps": 10_000_000}}, "steps"),
        (
            {
                "kind": "lavaland",
                "params": {"eval_maps": 65536, "train_maps": 65536, "repeats": 100},
            },
            "repeats",
        ),
        ({"kind": "cheetah", "params": {"trials": 200, "steps": 1_000_000}}, "trials"),
        (  # one trial a cell: its steps are what to lower
            {
                "kind": "cheetah",
                "params": {"trials": 1, "steps": 1_000_000, "backswing": [1, 2, 3, 4, 5, 6, 7, 8]}
                | {"inhibitor": [0, 1, 2, 3]},
            },
            "steps",
        ),
        (
            {"kind": "auction-study", "params": {"trials": 1000, "patrons": 1024, "grid": True}},
            "trials",
        ),
        (  # rules that never reach a stalemate: every auction plays its 1000 iterations
            {
                "kind": "auction-study",
                "params": {"rarities": [r / 100 for r in range(1, 101)], "trials": 1000}
                | {"max_iterations": 1000, "threshold_sell_price": 0, "decrement": 0.0001}
                | {"increment": 1000},
            },
            "trials",
        ),
        (  # every round fine-tunes (the default four cost 0.05 s an auction; these, minutes)
            {
                "kind": "auction-study",
                "params": {"fine_tune": True, "fine_tune_rounds": 1000, "max_iterations": 1000}
                | {"trials": 100},
            },
            "trials",
        ),
    ],
)
def test_jobs_over_the_budget_are_refused_naming_the_option(client, body, option) -> None:
    response = client.post("/jobs", json=body, headers=ADMIN)
    assert response.status_code == 422
    (item,) = response.json()["detail"]
    assert item["loc"] == ["body", "params", option]
    assert "SRD_JOB_BUDGET_S" in item["msg"] and f"lower {option} to at most" in item["msg"]


def test_a_job_over_the_budget_at_its_options_least_names_the_options_as_a_whole(
    client,
) -> None:
    """Even with one trial the run is over the budget: the error is the options' as a whole,
    not the one option it cannot lower."""
    params = {"trials": 1, "patrons": 1024, "rows": 256, "fine_tune": True}
    params |= {"fine_tune_rounds": 1000, "max_iterations": 1000, "screen": True}
    response = client.post("/jobs", json={"kind": "auction-study", "params": params}, headers=ADMIN)
    assert response.status_code == 422
    (item,) = response.json()["detail"]
    assert item["loc"] == ["body", "params"]
    assert "SRD_JOB_BUDGET_S" in item["msg"] and "with trials 1: lower the options" in item["msg"]


def test_every_kind_declares_its_cost() -> None:
    for kind in KINDS.values():
        cost = kind.config_class()().cost()
        assert 0 < cost.seconds < 1800, kind.name  # the defaults fit the default budget
        assert cost.option in {f.name for f in config_fields(kind.config_class())}


def test_an_auction_step_over_its_time_limit_is_stopped_and_failed(tmp_path) -> None:
    """The limit is per step, kept to the moment: the first step restores 160 patrons and plays
    and fine-tunes them through three iterations (about 0.3 s on an idle 2-core machine); a
    0.05 s limit stops it, whichever instant of the supervisor's tick it falls on."""
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    settings = settings.model_copy(update={"auction_timeout_s": 0.05})
    with TestClient(create_app(settings)) as client:
        ids = [
            client.post("/submit", json=honest(unique("slow"), seed=i)).json()["model_id"]
            for i in range(2, 162)  # seed 1 is held for review
        ]
        body = {"n_fish": 80, "model_ids": ids, "fine_tune": True}
        auction_id = client.post("/auctions", json=body, headers=ADMIN).json()["auction_id"]
        state = wait_for(
            lambda: client.get(f"/auctions/{auction_id}").json(),
            lambda a: a["status"] in ("finished", "failed"),
            60,
        )
    assert state["status"] == "failed"
    assert "time limit of 0.05 s (SRD_AUCTION_TIMEOUT_S)" in state["error"]


def test_a_job_over_its_memory_limit_fails_saying_so(tmp_path) -> None:
    """The OS refuses the worker more address space than SRD_JOB_MEMORY_MB: a lavaland job
    with 65536 maps of 16 plans needs more than 1500 MB."""
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    with TestClient(create_app(settings.model_copy(update={"job_memory_mb": 1500}))) as client:
        params = {"eval_maps": 65536, "train_maps": 0, "n_plans": 16}
        job = run_to_end(client, {"kind": "lavaland", "params": params}, timeout_s=300)
    assert job["status"] == "failed"
    assert (
        job["message"] == "failed: the job memory limit of 1500 MB (SRD_JOB_MEMORY_MB) was reached"
    )
    assert "can't allocate memory" in job["error"]


def test_past_the_queue_bound_a_job_is_refused_until_some_have_started(tmp_path) -> None:
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    settings = settings.model_copy(update={"max_queued_jobs": 2, "job_workers": 1})
    long = {"kind": "fish", "params": {"steps": 1_000_000}}  # minutes: holds the one worker
    with TestClient(create_app(settings)) as client:
        running = client.post("/jobs", json=long, headers=ADMIN).json()["job_id"]
        wait_for(
            lambda: client.get(f"/jobs/{running}").json(), lambda s: s["status"] == "running", 60
        )
        queued = [client.post("/jobs", json=long, headers=ADMIN) for _ in range(2)]
        assert [r.status_code for r in queued] == [202, 202]
        refused = client.post("/jobs", json=long, headers=ADMIN)
        assert refused.status_code == 503
        assert refused.headers["Retry-After"] == "30"
        (item,) = refused.json()["detail"]
        assert item["loc"] == ["server"] and item["type"] == "too_many_jobs"
        assert "2 jobs are waiting to run" in item["msg"] and "SRD_MAX_QUEUED_JOBS" in item["msg"]
        listed = client.get("/jobs").json()["items"]
        assert len(listed) == 3  # nothing stored for the refused one
        client.delete(f"/jobs/{queued[0].json()['job_id']}", headers=ADMIN)
        again = client.post("/jobs", json=long, headers=ADMIN)
        assert again.status_code == 202, again.text  # a slot came back
        for job in client.get("/jobs").json()["items"]:
            client.delete(f"/jobs/{job['id']}", headers=ADMIN)


def test_past_the_live_auction_bound_an_auction_is_refused_until_one_ends(tmp_path) -> None:
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    settings = settings.model_copy(update={"max_live_auctions": 2})
    with TestClient(create_app(settings)) as client:
        for _ in range(2):
            assert client.post("/submit", json=honest(unique("live"))).status_code == 201
        remote = {"n_fish": 1, "fine_tune_mode": "remote", "round_deadline_s": 300}
        live = [client.post("/auctions", json=remote, headers=ADMIN) for _ in range(2)]
        assert [r.status_code for r in live] == [201, 201]  # each waits in its first round
        refused = client.post("/auctions", json=remote, headers=ADMIN)
        assert refused.status_code == 503 and refused.headers["Retry-After"] == "30"
        (item,) = refused.json()["detail"]
        assert item["loc"] == ["server"] and item["type"] == "too_many_auctions"
        assert "SRD_MAX_LIVE_AUCTIONS" in item["msg"]
        assert len(client.get("/auctions").json()["items"]) == 2  # nothing stored
        client.delete(f"/auctions/{live[0].json()['auction_id']}", headers=ADMIN)
        again = client.post("/auctions", json=remote, headers=ADMIN)
        assert again.status_code == 201, again.text  # a cancelled auction is no longer live
        for auction in client.get("/auctions").json()["items"]:
            client.delete(f"/auctions/{auction['id']}", headers=ADMIN)


@pytest.mark.postgres
def test_racing_creations_keep_the_live_auction_bound(tmp_path) -> None:
    """Creations racing each other each count the others: no more auctions are pending or
    running than the bound, however many arrive at once (before, up to 3 over it)."""
    admin_url = postgres_admin_url()
    if admin_url is None:
        pytest.skip("PostgreSQL is not reachable on 127.0.0.1:5432")
    with throwaway_postgres(admin_url) as url:
        settings = make_settings(url, tmp_path / "data").model_copy(update={"max_live_auctions": 2})
        with TestClient(create_app(settings)) as client:
            model = client.post("/submit", json=honest(unique("race-live"))).json()
            enrolling = {"n_fish": 1, "enrollment_s": 600, "model_ids": [model["model_id"]]}
            start = threading.Barrier(10)

            def create(_: int) -> int:
                start.wait()
                return client.post("/auctions", json=enrolling, headers=ADMIN).status_code

            with ThreadPoolExecutor(10) as pool:
                statuses = list(pool.map(create, range(10)))
            assert sorted(statuses) == [201] * 2 + [503] * 8, statuses
            for auction in client.get("/auctions").json()["items"]:
                client.delete(f"/auctions/{auction['id']}", headers=ADMIN)


@pytest.mark.parametrize(
    ("value", "count"), [("," * 260_000, 260_001), ([""] * 60_000, 60_000), ("1," * 32, 33)]
)
def test_an_over_long_list_is_refused_on_its_count_alone(client, value, count) -> None:
    """One error naming the field and its bound, as a comma-separated string or an array,
    answered before any of its values is read."""
    body = {"kind": "cheetah", "params": {"backswing": value}}
    response = client.post("/jobs", json=body, headers=ADMIN)
    assert response.status_code == 422, response.text
    (item,) = response.json()["detail"]
    assert item["loc"] == ["body", "params", "backswing"]
    assert item["msg"] == f"{count} values: at most 32"


def test_a_lavaland_gif_map_past_the_evaluation_maps_is_refused_naming_it(client) -> None:
    """Map 300 of 256 is no map: refused, not drawn as another one (it was map 44)."""
    params = {"eval_maps": 256, "train_maps": 0, "gif_map": 300}
    response = client.post("/jobs", json={"kind": "lavaland", "params": params}, headers=ADMIN)
    assert response.status_code == 422, response.text
    (item,) = response.json()["detail"]
    assert item["loc"] == ["body", "params", "gif_map"]
    assert item["msg"].startswith("must be below eval-maps (256)")
    assert client.get("/jobs").json()["items"] == []


def test_a_design_stage_refuses_the_grid_axes_it_does_not_take(client) -> None:
    """A design stage runs its own conditions; only stage 4 takes ``backswing``."""
    cases = [
        ({"stage": 0, "lr": [0.01]}, "lr"),
        ({"stage": 1, "backswing": [9]}, "backswing"),
        ({"stage": 4, "srd": "off"}, "srd"),
        ({"stage": 2, "inhibitor": "0,5"}, "inhibitor"),
    ]
    for params, field in cases:
        response = client.post("/jobs", json={"kind": "cheetah", "params": params}, headers=ADMIN)
        assert response.status_code == 422, response.text
        (item,) = response.json()["detail"]
        assert item["loc"] == ["body", "params", field]
        assert f"does not take {field}" in item["msg"]
    assert client.get("/jobs").json()["items"] == []


def test_a_job_whose_files_grow_past_their_bound_is_failed_and_its_files_removed(
    tmp_path,
) -> None:
    """SRD_JOB_DISK_MB: a fish job's files (energy.csv, about 15 bytes a step, and a 40 kB
    plot) pass 0.1 MB; the job fails saying why, lists no artifacts, and its folder goes. A
    small job (50 kB) still succeeds."""
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    settings = settings.model_copy(update={"job_disk_mb": 0.1, "job_workers": 1})
    with TestClient(create_app(settings)) as client:
        job = run_to_end(client, {"kind": "fish", "params": {"steps": 8_000, "srd": False}})
        assert job["status"] == "failed", job
        assert "SRD_JOB_DISK_MB" in job["message"] and "more than the 0.1 MB" in job["message"]
        assert job["artifacts"] == []
        folder = settings.data_dir / "jobs" / str(job["id"])
        wait_for(lambda: {"kept": folder.exists()}, lambda s: not s["kept"], 15)
        assert client.get(f"/jobs/{job['id']}/artifacts/energy.csv").status_code == 404
        small = run_to_end(client, {"kind": "fish", "params": {"steps": 10}})
        assert small["status"] == "succeeded", small["error"]
        assert "energy.csv" in small["artifacts"]


@contextlib.contextmanager
def small_disk(folder: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` mounted on ``folder`` (root only: the test is skipped otherwise)."""
    folder.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small disk needs root")
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
        capture_output=True,
        text=True,
        check=False,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {mounted.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


@pytest.mark.slow  # `srd cheetah`'s own test of a GIF it cannot write runs by default
def test_a_cheetah_job_on_a_full_disk_fails_naming_its_file_and_leaves_no_gif(tmp_path) -> None:
    """The disk fills while the GIF is written (its other files fit in 64 kB, the GIF takes
    72 kB): the job fails saying so, the file named from its folder (the message is public: no
    path of the server's), and no truncated GIF is listed or kept."""
    with small_disk(tmp_path / "disk", "64k") as disk:
        settings = make_settings(
            f"sqlite:///{tmp_path / 'srd.db'}", disk / "data", min_free_disk_mb=0, job_workers=1
        )
        params = {"backswing": [4], "inhibitor": [2], "srd": "off", "trials": 1, "steps": 100}
        with TestClient(create_app(settings)) as client:
            job = run_to_end(client, {"kind": "cheetah", "params": params})
            note = (job["result"] or {}).get("video_note") or ""
            if job["status"] == "succeeded" and "No space left" not in note:
                pytest.skip(note)  # no OpenGL here: no GIF to write
            assert job["status"] == "failed", job
            error = "OSError: [Errno 28] No space left on device: 'cheetah.gif'"
            assert job["message"] == f"failed: {error}"
            assert job["error"].startswith(f"{error}\n") and str(tmp_path) not in job["error"]
            assert job["artifacts"] == []
            folder = settings.data_dir / "jobs" / str(job["id"])
            wait_for(lambda: {"kept": folder.exists()}, lambda s: not s["kept"], 15)


class DiesAtStart:
    """A worker's task that ends its process as the worker unpickles it (a worker that cannot
    start: a broken environment, an import that fails), before the worker begins any task."""

    def __init__(self) -> None:
        self.code = 3  # a state to unpickle: __setstate__ runs

    def __setstate__(self, state: dict[str, Any]) -> None:
        os._exit(state["code"])

    def __call__(self, context: Any, task_id: int) -> None:  # never reached
        raise AssertionError("a task began")


def test_a_job_whose_workers_cannot_start_fails_saying_so(tmp_path) -> None:
    """A worker that dies before it begins a job ran none of it: the job runs again, but not
    for ever: after three such deaths in a row it fails, saying its workers cannot start."""
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    with TestClient(create_app(settings.model_copy(update={"job_workers": 1}))) as client:
        client.app.state.services.jobs.pool._task = DiesAtStart()  # type: ignore[attr-defined]
        job = run_to_end(client, {"kind": "fish", "params": {"steps": 10}})
    assert job["status"] == "failed", job
    assert "its worker died before it began, 3 times in a row (last exit code 3)" in job["error"]


@pytest.mark.slow  # its neighbour, a worker that can never start, runs by default
def test_a_job_worker_the_system_refuses_to_start_is_tried_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A fork the system refuses (EAGAIN: a process limit) leaves the job queued and is tried
    again at the next pass; the job runs once a worker starts. The refusals in a row are
    logged the 1st, 2nd, 4th ... time, so a long refusal does not fill the log."""
    refusals = refuse_starts(monkeypatch, "srd-job-worker", 5)
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    with (
        caplog.at_level(logging.ERROR, logger="srd.workers"),
        TestClient(create_app(settings.model_copy(update={"job_workers": 1}))) as client,
    ):
        job = run_to_end(client, {"kind": "fish", "params": {"steps": 10}})
    assert job["status"] == "succeeded", job
    assert not refusals
    logged = [r.getMessage() for r in caplog.records if "worker failed" in r.getMessage()]
    assert logged == [
        f"job: starting or handing work to a worker failed ({n} times in a row)" for n in (1, 2, 4)
    ]
