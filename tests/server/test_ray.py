"""The Ray job backend on a throw-away local Ray cluster (loopback, token authentication on):
jobs give the local backend's numbers and artifacts for the same seeds, a cancelled job stops
its tasks, a unit whose Ray worker is killed runs again and the result is unchanged."""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from server.app import create_app
from server.cli.launch import ServerProcess
from server.jobs.ray_backend import RayUnavailableError, connect, ray_module
from tests.support.factories import honest
from tests.support.processes import descendants, process_name
from tests.support.ray_head import RayHead
from tests.support.server import ADMIN, ADMIN_TOKEN, make_settings, wait_for

# Not imported here: Ray reads its token settings once, when it is first imported.
pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason="the Ray extra is not installed: pip install '.[ray]'",
)

CPUS = 2
JOBS = {
    "auction-study": {"rarities": [0.3, 0.7], "trials": 4, "grid": True, "seed": 5},
    "lavaland": {"eval_maps": 64, "train_maps": 128, "repeats": 3, "seed": 1},
    "cheetah": {"backswing": [2.0, 4.0], "steps": 100, "trials": 10, "seed": 3},
}
"""Small jobs of several units each (auction-study 2, lavaland 3, cheetah 3)."""
LONG_LAVALAND = {"eval_maps": 1024, "train_maps": 32768, "repeats": 2, "seed": 4}
"""About ten seconds per unit: long enough to see its task run."""
RUN_TIMEOUT_S = 300
TIMES = ("elapsed_s", "simulation_s")


@pytest.fixture(scope="module")
def ray_head() -> Iterator[RayHead]:
    with RayHead(CPUS) as head:
        saved = {name: os.environ.get(name) for name in head.env}
        os.environ.update(head.env)  # the app (a driver) and its job workers present the token
        try:
            yield head
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value


def client_for(tmp: Path, **overrides: Any) -> TestClient:
    tmp.mkdir(exist_ok=True)  # the server does not make its database's folder
    settings = make_settings(
        f"sqlite:///{tmp / 'srd.db'}", tmp / "data", job_workers=3, **overrides
    )
    return TestClient(create_app(settings))


def start_lavaland(
    client: TestClient, head: RayHead, repeats: int, tasks: int = 1
) -> tuple[int, list[int]]:
    """A long lavaland job of ``repeats`` units, once ``tasks`` of them run on the cluster: its
    id and the pids of those tasks' Ray workers."""
    params = {**LONG_LAVALAND, "repeats": repeats}
    answer = client.post("/jobs", json={"kind": "lavaland", "params": params}, headers=ADMIN)
    running = wait_for(
        lambda: {"tasks": head.worker_pids("srd lavaland")},
        lambda seen: len(seen["tasks"]) >= tasks,
        RUN_TIMEOUT_S,
    )
    return int(answer.json()["job_id"]), list(running["tasks"])


def run_jobs(client: TestClient, jobs: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    ids = {}
    for kind, params in jobs.items():
        answer = client.post("/jobs", json={"kind": kind, "params": params}, headers=ADMIN)
        assert answer.status_code == 202, answer.text
        ids[kind] = answer.json()["job_id"]
    return {
        kind: wait_for(
            lambda i=job_id: client.get(f"/jobs/{i}").json(),
            lambda job: job["status"] not in ("queued", "running"),
            RUN_TIMEOUT_S,
        )
        for kind, job_id in ids.items()
    }


def numbers(value: Any) -> Any:
    """A result or JSON artifact without its wall times."""
    if isinstance(value, dict):
        return {k: numbers(v) for k, v in value.items() if k not in TIMES}
    if isinstance(value, list):
        return [numbers(v) for v in value]
    return value


def artifacts(data_dir: Path, job: dict[str, Any]) -> dict[str, Any]:
    """Every CSV, JSON and GIF artifact of a job (JSON without wall times)."""
    folder = data_dir / "jobs" / str(job["id"])
    found: dict[str, Any] = {}
    for name in job["artifacts"]:
        path = folder / name
        if path.suffix == ".json":
            found[name] = numbers(json.loads(path.read_text()))
        elif path.suffix in (".csv", ".gif"):
            found[name] = path.read_bytes()
    return found


@pytest.mark.slow  # three jobs on Ray and again locally; the default run keeps cancel and retry
def test_ray_jobs_equal_local_jobs(ray_head: RayHead, tmp_path: Path) -> None:
    with client_for(tmp_path / "local") as local:
        assert local.get("/healthz").json()["job_backend"] == "local"
        expected = run_jobs(local, JOBS)
    ray = tmp_path / "ray"
    with client_for(ray, job_backend="ray", ray_address=ray_head.address) as client:
        health = client.get("/healthz").json()
        assert health == {
            "status": "ok",
            "problems": [],
            "job_backend": "ray",
            "cpus": float(CPUS),
            "screener_populations": "public",
        }
        done = run_jobs(client, JOBS)
    for kind, job in done.items():
        mine = expected[kind]
        assert job["status"] == "succeeded" == mine["status"], (kind, job["error"], mine["error"])
        assert job["message"] == "done"
        assert numbers(job["result"]) == numbers(mine["result"]), kind
        assert job["artifacts"] == mine["artifacts"], kind
        assert artifacts(ray / "data", job) == artifacts(tmp_path / "local" / "data", mine), kind
    assert "cheetah.gif" in done["cheetah"]["artifacts"]  # the filmed trial came from a unit


@pytest.mark.slow  # a cheetah job on Ray; cancelling a Ray job runs by default
def test_a_unit_asking_more_cpus_than_any_node_has_runs_on_the_largest(
    ray_head: RayHead, tmp_path: Path
) -> None:
    """A cheetah unit keeps ``threads`` CPUs busy; asking more than any node has, its task
    waited for ever (the job ``running`` until its time limit, every job behind it queued):
    it runs on the largest node's CPUs, with the local backend's numbers."""
    params = {"backswing": [3.0], "inhibitor": [0.0], "srd": "off", "trials": 2, "steps": 100}
    params |= {"threads": CPUS + 2, "video": False, "seed": 2}
    with client_for(tmp_path / "ray", job_backend="ray", ray_address=ray_head.address) as client:
        done = run_jobs(client, {"cheetah": params})["cheetah"]
    assert done["status"] == "succeeded", done
    with client_for(tmp_path / "local") as client:
        expected = run_jobs(client, {"cheetah": params})["cheetah"]
    assert numbers(done["result"]["runs"]) == numbers(expected["result"]["runs"])


def test_cancelling_a_ray_job_stops_its_tasks(
    ray_head: RayHead, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    with client_for(tmp_path, job_backend="ray", ray_address=ray_head.address) as client:
        job_id, running = start_lavaland(client, ray_head, 4, tasks=CPUS)
        cancelled = client.delete(f"/jobs/{job_id}", headers=ADMIN)
        assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
        wait_for(
            lambda: {"tasks": ray_head.worker_pids("srd lavaland")},
            lambda seen: not seen["tasks"],
            15,
        )
        for pid in running:  # force-cancelled: their worker processes are gone
            assert (
                not Path(f"/proc/{pid}").exists()
                or b"srd lavaland" not in Path(f"/proc/{pid}/cmdline").read_bytes()
            )
        time.sleep(1)
        assert client.get(f"/jobs/{job_id}").json()["status"] == "cancelled"
    # the job worker (a Ray driver) stopped quietly: no stack dump of Ray's for its SIGTERM
    assert "SIGTERM received" not in capfd.readouterr().err


@pytest.mark.slow  # a job run twice on Ray; cancelling one (its SIGTERM) runs by default
def test_a_ray_job_whose_worker_is_stopped_from_outside_runs_again(
    ray_head: RayHead, tmp_path: Path
) -> None:
    """A service manager stops every process of the service with SIGTERM: a job worker that
    is a Ray driver, so stopped, is counted as stopped, not failed, and its job runs again, as
    on the local backend (it had failed: "the job worker exited (code 15) without a result")."""
    with client_for(tmp_path, job_backend="ray", ray_address=ray_head.address) as client:
        job_id, _ = start_lavaland(client, ray_head, 1)
        workers = [p for p in descendants(os.getpid()) if process_name(p) == "srd-job-worker"]
        assert workers
        for worker in workers:
            os.kill(worker, signal.SIGTERM)
        done = wait_for(
            lambda: client.get(f"/jobs/{job_id}").json(),
            lambda job: job["status"] not in ("queued", "running"),
            RUN_TIMEOUT_S,
        )
        assert done["status"] == "succeeded", done["error"]
        assert not any(map(process_name, workers))  # stopped: another worker ran the job


@pytest.mark.slow  # a cluster of its own, stopped under a running job
def test_a_ray_cluster_lost_mid_job_fails_the_job_naming_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The cluster stops while a job's units run. However Ray takes it (an error in the wait
    for a unit, or the driver ended by Ray with code 1), the job fails saying that the cluster
    was lost and where it was (it said only "the job worker exited (code 1) without a
    result")."""
    with RayHead(1) as head:
        for name, value in head.env.items():
            monkeypatch.setenv(name, value)
        with client_for(tmp_path, job_backend="ray", ray_address=head.address) as client:
            job_id, _ = start_lavaland(client, head, 4)
            head.stop()
            done = wait_for(
                lambda: client.get(f"/jobs/{job_id}").json(),
                lambda job: job["status"] not in ("queued", "running"),
                90,
            )
    assert done["status"] == "failed", done
    said = f"{done['message']} {done['error']}"
    assert re.search(
        rf"(the|its) Ray cluster (at '{head.address}' \(SRD_RAY_ADDRESS\) )?was lost", said
    ), done
    assert head.address in said, done


@pytest.mark.slow
def test_a_killed_ray_worker_unit_runs_again_with_the_same_result(
    ray_head: RayHead, tmp_path: Path
) -> None:
    job = {"lavaland": LONG_LAVALAND}
    with client_for(tmp_path / "local") as local:
        (expected,) = run_jobs(local, job).values()
    ray = tmp_path / "ray"
    with client_for(ray, job_backend="ray", ray_address=ray_head.address) as client:
        answer = client.post(
            "/jobs", json={"kind": "lavaland", "params": LONG_LAVALAND}, headers=ADMIN
        )
        job_id = answer.json()["job_id"]
        seen = wait_for(
            lambda: {"tasks": ray_head.worker_pids("srd lavaland: repeat 1")},
            lambda s: bool(s["tasks"]),
            RUN_TIMEOUT_S,
        )
        killed = seen["tasks"][0]
        os.kill(killed, signal.SIGKILL)
        wait_for(  # Ray runs the lost unit again, in another worker
            lambda: {"tasks": set(ray_head.worker_pids("srd lavaland: repeat 1")) - {killed}},
            lambda s: bool(s["tasks"]),
            RUN_TIMEOUT_S,
        )
        done = wait_for(
            lambda: client.get(f"/jobs/{job_id}").json(),
            lambda j: j["status"] not in ("queued", "running"),
            RUN_TIMEOUT_S,
        )
    assert done["status"] == "succeeded", done["error"]
    assert numbers(done["result"]) == numbers(expected["result"])
    assert artifacts(ray / "data", done) == artifacts(tmp_path / "local" / "data", expected)


def test_a_unit_whose_worker_dies_every_try_fails_the_job_saying_its_retries_ran_out(
    ray_head: RayHead, tmp_path: Path
) -> None:
    """No retry left (``SRD_RAY_MAX_RETRIES`` 0) and its worker killed: the job fails saying
    the worker died every try it had, not with Ray's bare ``WorkerCrashedError``."""
    settings = {"job_backend": "ray", "ray_address": ray_head.address, "ray_max_retries": 0}
    with client_for(tmp_path, **settings) as client:
        job_id, workers = start_lavaland(client, ray_head, LONG_LAVALAND["repeats"])
        os.kill(workers[0], signal.SIGKILL)
        done = wait_for(
            lambda: client.get(f"/jobs/{job_id}").json(),
            lambda j: j["status"] not in ("queued", "running"),
            RUN_TIMEOUT_S,
        )
    assert done["status"] == "failed", done
    assert (
        "a unit's Ray worker died 1 time, every try it had (SRD_RAY_MAX_RETRIES=0)"
        in (done["error"])
    ), done["error"]


def test_ray_asked_for_but_missing_or_unaddressed_says_what_to_do(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now fails
    with pytest.raises(RayUnavailableError, match=r"pip install '\.\[ray\]'"):
        ray_module()
    monkeypatch.delitem(sys.modules, "ray")
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    with pytest.raises(ValidationError, match="SRD_JOB_BACKEND=ray needs SRD_RAY_ADDRESS"):
        client_for(tmp_path, job_backend="ray", ray_address=None)  # the settings refuse it


def test_a_ray_address_nobody_answers_stops_the_start_within_its_timeout(tmp_path: Path) -> None:
    """Ray waits forever for an address nobody answers on; the server's look at the cluster
    gives up after ``SRD_RAY_JOIN_TIMEOUT_S`` and the start fails naming the address."""
    with socket.socket() as held:  # a port nothing answers on
        held.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{held.getsockname()[1]}"
        started = time.monotonic()
        with pytest.raises(RayUnavailableError, match=re.escape(address)):  # noqa: SIM117
            with client_for(tmp_path, job_backend="ray", ray_address=address, ray_join_timeout_s=5):
                pass
    assert time.monotonic() - started < 30


def test_a_job_worker_facing_a_head_that_does_not_answer_fails_at_once(ray_head: RayHead) -> None:
    """Ray retries an address nobody answers on for minutes, and the job sat in ``running``
    meanwhile; a job's worker now asks the head first and fails naming it. (``ray_head``: Ray
    reads its token settings when first imported, here by ``connect``.)"""
    with socket.socket() as held:  # bound, not listening: the connection is refused
        held.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{held.getsockname()[1]}"
        started = time.monotonic()
        with pytest.raises(RayUnavailableError, match=re.escape(address)):
            connect(address, 5)
    assert time.monotonic() - started < 5


def test_the_clusters_probe_ends_with_the_job_worker_that_started_it() -> None:
    """The look at the cluster runs in a child process, which waits up to the join timeout
    for a head that takes connections and never answers. A job worker killed meanwhile (its
    job cancelled) took it along no more: it lived on, adopted by init, as long as the head
    hung. It now ends with its parent, as every child of a job worker does."""
    code = "import sys\nfrom server.jobs.ray_backend import probe_cpus\nprobe_cpus(sys.argv[1], 60)"
    with socket.socket() as silent:  # takes connections, answers nothing: a frozen head
        silent.bind(("127.0.0.1", 0))
        silent.listen(16)
        address = f"127.0.0.1:{silent.getsockname()[1]}"
        worker = subprocess.Popen(
            [sys.executable, "-c", code, address], cwd=Path(__file__).resolve().parents[2]
        )
        probes: list[int] = []
        try:
            deadline = time.monotonic() + 30
            while len(probes := descendants(worker.pid)[1:]) == 0:
                assert time.monotonic() < deadline, "the probe never started"
                time.sleep(0.05)
            time.sleep(1.0)  # well into its wait
            worker.kill()
            worker.wait(timeout=10)
            deadline = time.monotonic() + 5
            while alive := [pid for pid in probes if process_name(pid) not in (None, "")]:
                assert time.monotonic() < deadline, f"the probe {alive} outlived its worker"
                time.sleep(0.05)
        finally:
            worker.kill()
            for pid in probes:  # whatever became of them (adopted by init, without the fix)
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)


@pytest.mark.slow  # a cluster of its own: a head frozen a while is not one to share
def test_a_job_worker_facing_a_frozen_head_fails_within_its_join_timeout() -> None:
    """A head that takes the connection and never answers (its GCS stopped): ``ray.init``
    waits for ever, and the job sat in ``running`` until its time limit (an hour by default);
    the worker's join now gives up after ``SRD_RAY_JOIN_TIMEOUT_S``, naming the address."""
    code = (
        "import sys\n"
        "from server.jobs.ray_backend import RayUnavailableError, connect\n"
        "try:\n"
        "    connect(sys.argv[1], 5)\n"
        "except RayUnavailableError as exc:\n"
        "    print(exc)\n"
    )
    with RayHead(1) as head:
        gcs = [pid for pid, (_, command) in head._descendants().items() if "gcs_server" in command]
        assert gcs
        for pid in gcs:
            os.kill(pid, signal.SIGSTOP)
        try:
            started = time.monotonic()
            done = subprocess.run(
                [sys.executable, "-c", code, head.address],
                capture_output=True, text=True, timeout=120, env={**os.environ, **head.env},
                cwd=Path(__file__).resolve().parents[2],
            )  # fmt: skip
            took = time.monotonic() - started
        finally:
            for pid in gcs:
                os.kill(pid, signal.SIGCONT)
    assert f"cannot join the Ray cluster at {head.address!r}" in done.stdout, done.stderr[-2000:]
    assert "no answer within 5 s (SRD_RAY_JOIN_TIMEOUT_S)" in done.stdout
    assert took < 30


@pytest.mark.slow
def test_the_server_outlives_its_ray_cluster(tmp_path: Path) -> None:
    """The server never joins the cluster itself (Ray ends a driver whose cluster has been
    gone a minute): with the head stopped for longer, it serves on, says 0 CPUs, and a job
    started meanwhile fails with the reason."""
    with RayHead(1) as head:
        env = {**head.env, "SRD_JOB_BACKEND": "ray", "SRD_RAY_ADDRESS": head.address}
        env |= {"SRD_RAY_JOIN_TIMEOUT_S": "10"}
        server = ServerProcess(
            database_url=f"sqlite:///{tmp_path / 'srd.db'}",
            data_dir=tmp_path / "data",
            admin_token=ADMIN_TOKEN,
            extra_env=env,
        )
        with server, httpx.Client(base_url=server.url) as api:
            assert api.get("/healthz").json()["cpus"] == 1.0
            head.stop()
            time.sleep(75)  # past Ray's 60 s for a driver without its cluster
            assert server.process is not None and server.process.poll() is None, "it exited"
            health = wait_for(
                lambda: api.get("/healthz", timeout=5).json(),
                lambda h: h["cpus"] == 0.0,
                60,
            )
            assert health["status"] == "ok"  # auctions and submissions go on
            submitted = api.post("/submit", json=honest("after-ray", seed=0), timeout=30)
            assert submitted.status_code == 201, submitted.text
            body = {"kind": "fish", "params": {"steps": 500, "seed": 1}}
            job_id = api.post("/jobs", json=body, headers=ADMIN).json()["job_id"]
            job = wait_for(
                lambda: api.get(f"/jobs/{job_id}").json(),
                lambda j: j["status"] not in ("queued", "running"),
                60,
            )
            assert job["status"] == "failed", job
            assert "cannot join the Ray cluster" in json.dumps(job["error"]), job
