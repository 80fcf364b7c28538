"""Bounded, loud jobs: a job over its time limit is stopped and failed saying so; a job that
fails for a real cause carries that cause (type and message), stored by its worker."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from tests.server.conftest import ADMIN, make_settings, wait_for

ENDED = {"succeeded", "failed", "cancelled"}


def run_to_end(client: TestClient, body: dict[str, Any], timeout_s: float = 120) -> dict[str, Any]:
    created = client.post("/jobs", json=body, headers=ADMIN)
    assert created.status_code == 202, created.text
    job_id = created.json()["job_id"]
    return wait_for(
        lambda: client.get(f"/jobs/{job_id}").json(), lambda s: s["status"] in ENDED, timeout_s
    )


@pytest.fixture
def limited(tmp_path) -> Any:
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    settings = settings.model_copy(update={"job_timeout_s": 10.0, "job_workers": 1})
    with TestClient(create_app(settings)) as client:
        yield client, settings


def test_a_job_over_its_time_limit_is_stopped_and_failed(limited) -> None:
    client, _ = limited
    job = run_to_end(client, {"kind": "fish", "params": {"steps": 200_000}})
    assert job["status"] == "failed"
    assert job["message"] == "failed"
    assert "time limit of 10 s (SRD_JOB_TIMEOUT_S)" in job["error"]
    quick = run_to_end(client, {"kind": "fish", "params": {"steps": 50}})
    assert quick["status"] == "succeeded"  # the pool carries on


def test_a_real_failure_is_stored_with_its_cause(limited) -> None:
    client, settings = limited
    jobs = settings.data_dir / "jobs"
    jobs.parent.mkdir(parents=True, exist_ok=True)
    jobs.write_text("a file where the job folders should be")
    job = run_to_end(client, {"kind": "fish", "params": {"steps": 50}})
    assert job["status"] == "failed"
    assert job["message"].startswith(("failed: FileExistsError", "failed: NotADirectoryError"))
    assert "Traceback" in job["error"] and str(jobs) in job["error"]
