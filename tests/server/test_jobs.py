"""Job lifecycle through the API: run, artifacts, cancel (queued and running), crashed worker.

Uses the ``fish`` kind (the robot fish is cheap at a few hundred steps).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import time
from datetime import datetime, timedelta
from email.utils import parsedate_to_datetime
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.config import Settings
from tests.support.openapi import assert_documented
from tests.support.server import ADMIN, make_settings, wait_for

LONG_FISH = {"kind": "fish", "params": {"steps": 200_000, "srd": True}}  # minutes: always stopped
SHORT_FISH = {"kind": "fish", "params": {"steps": 300, "srd": True, "seed": 4}}
JOB_TIMEOUT_S = 120


def start(client: TestClient, body: dict[str, Any]) -> int:
    response = client.post("/jobs", json=body, headers=ADMIN)
    assert response.status_code == 202, response.text
    assert response.json()["status"] == "queued"
    return int(response.json()["job_id"])


def job(client: TestClient, job_id: int) -> dict[str, Any]:
    response = client.get(f"/jobs/{job_id}")
    assert response.status_code == 200
    return dict(response.json())


def pid_of(client: TestClient, job_id: int) -> int | None:
    return client.app.state.services.jobs.pool.pid(job_id)  # type: ignore[attr-defined,no-any-return]


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def assert_no_escape(client: TestClient, job_id: int, settings: Settings) -> None:
    """Only listed artifact names are served; nothing outside the job's folder."""
    (settings.data_dir / "secret.txt").write_text("top secret")
    (settings.data_dir / "jobs" / str(job_id) / "unlisted.txt").write_text("not an artifact")
    for name in (
        "../../secret.txt",
        "..%2F..%2Fsecret.txt",
        "%2E%2E/%2E%2E/secret.txt",
        "/etc/passwd",
        "%2Fetc%2Fpasswd",
        "unlisted.txt",
        "fish.png/..",
        ".",
        "",
    ):
        response = client.get(f"/jobs/{job_id}/artifacts/{name}")
        # the client may resolve plain dot segments itself (another route then answers 4xx)
        expected = (404, 422) if name.startswith("../") else (404,)
        assert response.status_code in expected, name
        assert b"top secret" not in response.content and b"root:" not in response.content


@pytest.mark.postgres_in_slow_run  # jobs on PostgreSQL: test_votes' job list, test_replicas
def test_job_lifecycle(
    client: TestClient, settings: Settings, caplog: pytest.LogCaptureFixture
) -> None:
    """Two workers. A long job is killed -9 mid-run (fails), a short one runs to the end, a third
    is cancelled while queued, a fourth is cancelled while running (its process ends)."""
    caplog.set_level(logging.INFO)
    is_running = lambda j: j["status"] == "running"  # noqa: E731
    crashing = start(client, LONG_FISH)
    short = start(client, SHORT_FISH)
    waiting = start(client, LONG_FISH)
    assert job(client, waiting)["status"] == "queued"
    cancelled = client.delete(f"/jobs/{waiting}", headers=ADMIN)
    assert cancelled.status_code == 200 and cancelled.json()["status"] == "cancelled"
    again = client.delete(f"/jobs/{waiting}", headers=ADMIN)
    assert again.status_code == 409 and "already cancelled" in again.json()["detail"][0]["msg"]

    state = wait_for(lambda: job(client, crashing), is_running, JOB_TIMEOUT_S)
    assert state["started_at"] is not None
    pid = pid_of(client, crashing)
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    state = wait_for(lambda: job(client, crashing), lambda j: not is_running(j), 30)
    assert state["status"] == "failed" and "code -9" in state["error"]

    running = start(client, LONG_FISH)  # takes the freed worker slot
    wait_for(lambda: job(client, running), is_running, JOB_TIMEOUT_S)
    pid = pid_of(client, running)
    assert pid is not None and alive(pid)
    response = client.delete(f"/jobs/{running}", headers=ADMIN)
    assert response.status_code == 200 and response.json()["status"] == "cancelled"
    wait_for(lambda: {"alive": alive(pid)}, lambda s: not s["alive"], 15)
    assert job(client, running)["status"] == "cancelled"
    assert job(client, waiting)["started_at"] is None  # the queued one never ran
    logged = caplog.messages
    assert f"job {waiting} cancelled" in logged and f"job {running} cancelled" in logged

    done = wait_for(
        lambda: job(client, short),
        lambda j: j["status"] not in ("queued", "running"),
        JOB_TIMEOUT_S,
    )
    assert done["status"] == "succeeded", done["error"]
    assert done["progress"] == 1.0 and done["error"] is None
    assert done["params"]["steps"] == 300 and done["params"]["seed"] == 4
    result = done["result"]
    assert result["steps"] == 300 and result["srd"] is True and result["died"] is False
    assert 0.0 < result["mean_energy_first_1000"] <= 1.0
    assert {"result.json", "fish.png"} <= set(done["artifacts"])
    # An ended job reads the same every time (from the second read on, its JSON is kept).
    reads = [client.get(f"/jobs/{short}") for _ in range(3)]
    assert all(r.headers["content-type"] == "application/json" for r in reads)
    assert reads[0].content == reads[1].content == reads[2].content
    assert reads[2].json() == done
    stored = client.get(f"/jobs/{short}/artifacts/result.json")
    assert stored.status_code == 200 and json.loads(stored.content) == result
    png = client.get(f"/jobs/{short}/artifacts/fish.png")
    assert png.headers["content-type"] == "image/png" and png.content[:4] == b"\x89PNG"
    document = client.get("/openapi.json").json()  # each answer below is one it lists
    route = "/jobs/{job_id}/artifacts/{name}"
    for spelt in ("bytes=0-3", "BYTES=0-3", "bytes=0-3, 8-"):
        part = client.get(f"/jobs/{short}/artifacts/fish.png", headers={"Range": spelt})
        assert part.status_code == 206 and b"\x89PNG" in part.content, spelt
    assert_documented(document, route, client.get(f"/jobs/{short}/artifacts/fish.png",
                                                  headers={"Range": "bytes=0-3"}))  # fmt: skip
    unsatisfiable = {"Range": "bytes=999999999-"}
    refused = client.get(f"/jobs/{short}/artifacts/fish.png", headers=unsatisfiable)
    assert refused.status_code == 416, refused.text  # in JSON
    assert refused.json()["detail"][0]["loc"] == ["header", "Range"]
    assert_documented(document, route, refused)
    malformed = ("bytes=1_0-20", "bytes=+1-2", "bytes=0-1_0", "bytes= 1-2")  # int() read them
    for ignored in ("lines=1-2", "items=0-1", "bytes=5-2", "bytes=x", *malformed):  # RFC 9110
        whole = client.get(f"/jobs/{short}/artifacts/fish.png", headers={"Range": ignored})
        assert whole.status_code == 200 and whole.content == png.content, ignored
    # Preconditions (RFC 9110, 13.2): its validators are evaluated.
    url = f"/jobs/{short}/artifacts/fish.png"
    etag, modified = png.headers["etag"], png.headers["last-modified"]
    for asked in ({"If-None-Match": etag}, {"If-None-Match": f"W/{etag}, \"x\""},
                  {"If-Modified-Since": modified}, {"If-None-Match": "*"}):  # fmt: skip
        same = client.get(url, headers=asked)
        assert same.status_code == 304 and same.content == b"", asked
        assert same.headers["etag"] == etag
        assert_documented(document, route, same)
    for asked in ({"If-Match": '"nope"'}, {"If-Unmodified-Since": "Sat, 01 Jan 2000 00:00:00 GMT"}):
        failed = client.get(url, headers=asked)
        assert failed.status_code == 412, asked
        (item,) = failed.json()["detail"]
        assert item["type"] == "precondition" and item["loc"] == ["header", *asked], item
        assert_documented(document, route, failed)
    for asked in ({"If-None-Match": '"other"'}, {"If-Match": etag}, {"If-Modified-Since": "x"}):
        assert client.get(url, headers=asked).status_code == 200, asked
    # RFC 9110's obsolete date forms, which carry no zone (GMT all the same), are read too.
    later = parsedate_to_datetime(modified) + timedelta(days=1)
    for form in (
        "%a %b %d %H:%M:%S %Y",
        "%A, %d-%b-%y %H:%M:%S GMT",
        "%a, %d %b %Y %H:%M:%S -0000",
    ):
        assert (
            client.get(url, headers={"If-Modified-Since": later.strftime(form)}).status_code == 304
        ), form
        long_ago = {"If-Unmodified-Since": datetime(1999, 1, 1).strftime(form)}
        assert client.get(url, headers=long_ago).status_code == 412, form
    page = client.get("/", headers={"If-Modified-Since": "Mon Jan  1 00:00:00 1900"})
    assert page.status_code == 200 and "srd-auction" in page.text
    for header in ("If-Modified-Since", "If-Unmodified-Since"):  # a year past any date: ignored
        huge = {header: "Mon, 01 Jan 99999999999 00:00:00 GMT"}
        assert client.get("/", headers=huge).status_code == 200
    long_name = client.get(f"/jobs/{short}/artifacts/{'x' * 5000}")
    assert long_name.status_code == 404 and len(long_name.content) < 500
    assert client.delete(f"/jobs/{short}", headers=ADMIN).status_code == 409
    assert_no_escape(client, short, settings)


def test_a_stopped_job_leaves_no_files(client: TestClient, settings: Settings) -> None:
    """A cancelled job's folder is removed with what its run had written so far; the job keeps
    its status and message, lists no artifacts, and serves none."""
    job_id = start(client, LONG_FISH)
    wait_for(lambda: job(client, job_id), lambda j: j["status"] == "running", JOB_TIMEOUT_S)
    folder = settings.data_dir / "jobs" / str(job_id)
    wait_for(lambda: {"made": folder.is_dir()}, lambda s: s["made"], 30)
    (folder / "runs.csv").write_text("trial\n1\n")  # as a run writes its files before its end
    assert client.delete(f"/jobs/{job_id}", headers=ADMIN).status_code == 200
    wait_for(lambda: {"kept": folder.exists()}, lambda s: not s["kept"], 15)
    state = job(client, job_id)
    assert state["status"] == "cancelled" and state["message"] == "cancelled"
    assert state["artifacts"] == []
    assert client.get(f"/jobs/{job_id}/artifacts/runs.csv").status_code == 404


def test_a_long_silent_phase_shows_its_own_progress(tmp_path: Path) -> None:
    """At most one progress write per SRD_PROGRESS_INTERVAL_S (an hour here), besides the first
    report of each phase: once its steps are done, a cheetah job says it writes its artifacts
    and draws its figures (seconds without a report), not the step it was at an hour ago."""
    settings = make_settings(
        f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data", progress_interval_s=3600.0
    )
    params = {"backswing": [3], "inhibitor": [2], "srd": "off", "trials": 1, "steps": 300}
    seen: list[str] = []
    with TestClient(create_app(settings)) as client:
        job_id = start(client, {"kind": "cheetah", "params": params | {"video": False}})
        state = job(client, job_id)
        while state["status"] in ("queued", "running"):
            if not seen or seen[-1] != state["message"]:
                seen.append(state["message"])
            time.sleep(0.005)
            state = job(client, job_id)
    assert state["status"] == "succeeded", state["error"]
    assert "drawing the figures" in seen, seen


EVERY_KIND = {
    "lavaland": (
        {"eval_maps": 16, "train_maps": 4, "seed": 1},
        {"project", "preset", "n_params", "accuracy_untrained", "accuracy_srd"},
    ),
    "cheetah": (
        {
            "backswing": [3],
            "inhibitor": [0, 2],
            "srd": "on",
            "trials": 1,
            "steps": 300,
            "video": False,
        },
        {"runs", "elapsed_s"},
    ),
    "auction-study": ({"rarities": [0.5], "trials": 1, "patrons": 8}, {"rows", "auctions"}),
    "comparison": (
        {"rarities": [0.5], "trials": 1, "patrons": 8, "buy_fraction": "staying"},
        {"configurations", "rows", "caption"},
    ),
}


@pytest.mark.postgres_in_slow_run
@pytest.mark.parametrize("kind", sorted(EVERY_KIND))
def test_every_kind_runs_as_a_job(client: TestClient, kind: str) -> None:
    """Each experiment kind runs through the job backend at a tiny budget: progress reaches 1,
    the result is the CLI's --json object and the artifacts are listed."""
    params, keys = EVERY_KIND[kind]
    job_id = start(client, {"kind": kind, "params": params})
    done = wait_for(
        lambda: job(client, job_id),
        lambda j: j["status"] not in ("queued", "running"),
        JOB_TIMEOUT_S,
    )
    assert done["status"] == "succeeded", done["error"]
    assert done["progress"] == 1.0
    assert keys <= set(done["result"])
    assert "result.json" in done["artifacts"] and len(done["artifacts"]) > 1
    if kind == "comparison":
        assert done["result"]["buy_fraction"] == "staying"
        assert "honest-alone" in done["result"]["configurations"]
    if kind == "lavaland":
        assert done["result"]["n_params"] == 180
    if kind == "cheetah":
        assert len(done["result"]["runs"]) == 2
