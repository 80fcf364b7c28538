"""Readiness and liveness: ``/healthz`` answers 503 naming each problem (a data folder that
cannot be written, too little free disk), ``/livez`` 200 all along; the answer is cached; a
data folder that cannot be written stops ``srd serve`` at start with one line and exit code 2."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server.api import readiness
from server.app import create_app
from server.cli.launch import free_port, srd_command
from server.config import Settings
from tests.support.server import make_settings


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")


def test_ready_then_data_folder_replaced_by_a_file(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(readiness, "CACHE_S", 0.0)
    with TestClient(create_app(settings)) as client:
        health = client.get("/healthz")
        assert health.status_code == 200
        assert health.json()["status"] == "ok" and health.json()["problems"] == []
        moved = settings.data_dir.with_name("moved")
        settings.data_dir.rename(moved)
        settings.data_dir.write_text("not a folder")  # root ignores mode bits: this it cannot
        health = client.get("/healthz")
        assert health.status_code == 503 and health.headers["retry-after"]
        body = health.json()
        assert body["status"] == "unavailable"
        [problem] = body["problems"]
        assert problem["check"] == "data_dir"
        assert str(settings.data_dir.resolve()) in problem["msg"]
        assert "cannot be written" in problem["msg"]
        assert client.get("/livez").json() == {"status": "ok"}
        settings.data_dir.unlink()
        moved.rename(settings.data_dir)
        assert client.get("/healthz").status_code == 200


def test_too_little_free_disk(tmp_path: Path) -> None:
    free_mb = shutil.disk_usage(tmp_path).free // (1 << 20)
    over = make_settings(
        f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data", min_free_disk_mb=free_mb + 1024
    )
    with TestClient(create_app(over)) as client:
        health = client.get("/healthz")
        assert health.status_code == 503
        problems = health.json()["problems"]
        assert {p["check"] for p in problems} == {"disk"}
        assert any(f"SRD_MIN_FREE_DISK_MB={free_mb + 1024}" in p["msg"] for p in problems)
        assert any(str((tmp_path / "data").resolve()) in p["msg"] for p in problems)
        assert client.get("/livez").status_code == 200
        assert client.post("/submit", json={}).status_code == 422  # still serving


def test_the_answer_is_cached(settings: Settings, monkeypatch: pytest.MonkeyPatch) -> None:
    checks = 0
    real = readiness.data_dir_problem

    def counted(path: Path) -> str | None:
        nonlocal checks
        checks += 1
        return real(path)

    monkeypatch.setattr(readiness, "data_dir_problem", counted)
    monkeypatch.setattr(readiness, "CACHE_S", 60.0)
    with TestClient(create_app(settings)) as client:
        for _ in range(50):
            assert client.get("/healthz").status_code == 200
    assert checks == 1


@pytest.mark.parametrize("where", ["file", "under_a_file"])
def test_serve_refuses_a_data_folder_it_cannot_write(tmp_path: Path, where: str) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    data_dir = blocker if where == "file" else blocker / "data"
    env = {
        **os.environ,  # PYTHONPATH: this working copy's code
        "SRD_DATA_DIR": str(data_dir),
        "SRD_DATABASE_URL": f"sqlite:///{tmp_path / 'srd.db'}",
    }
    done = subprocess.run(
        [*srd_command(), "serve", "--port", str(free_port())],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stdout == ""
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert str(data_dir) in lines[0] and "SRD_DATA_DIR" in lines[0]
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "srd.db").exists()  # stopped before anything was started
