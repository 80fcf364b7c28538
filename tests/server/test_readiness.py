"""Readiness and liveness: ``/healthz`` answers 503 naming each problem (a data folder that
cannot be written, too little free disk), ``/livez`` 200 all along; the answer is cached; a
data folder that cannot be written stops ``srd serve`` at start with one line and exit code 2."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server.api import readiness
from server.app import create_app
from server.config import Settings
from server.screening import pool
from tests.support.factories import honest
from tests.support.processes import serve_once
from tests.support.server import ADMIN, make_settings


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
        # Gone: its disk's free space cannot be read, and a job is refused saying so (not as
        # a full disk), nothing stored.
        job = {"kind": "fish", "params": {"steps": 10}}
        refused = client.post("/jobs", json=job, headers=ADMIN)
        assert refused.status_code == 503 and refused.headers["retry-after"], refused.text
        [item] = refused.json()["detail"]
        assert item["type"] == "disk_unreadable" and "cannot be read" in item["msg"], item
        assert str(settings.data_dir.parent) not in item["msg"]
        assert client.get("/jobs").json()["items"] == []
        settings.data_dir.write_text("not a folder")  # root ignores mode bits: this it cannot
        health = client.get("/healthz")
        assert health.status_code == 503 and health.headers["retry-after"]
        body = health.json()
        assert body["status"] == "unavailable"
        [problem] = body["problems"]
        assert problem["check"] == "data_dir"
        assert problem["msg"].startswith("the data folder (SRD_DATA_DIR) cannot be written: ")
        assert str(settings.data_dir.parent) not in problem["msg"]  # public: no install path
        assert client.get("/livez").json() == {"status": "ok"}
        settings.data_dir.unlink()
        moved.rename(settings.data_dir)
        assert client.get("/healthz").status_code == 200


def test_too_little_free_disk(tmp_path: Path) -> None:
    """Not ready, naming the setting and each folder by its role: ``/healthz`` is public, and
    a path would say where the server is installed (``POST /jobs`` says the same)."""
    free_mb = shutil.disk_usage(tmp_path).free // (1 << 20)
    over = make_settings(
        f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data", min_free_disk_mb=free_mb + 1024
    )
    with TestClient(create_app(over)) as client:
        health = client.get("/healthz")
        assert health.status_code == 503
        problems = health.json()["problems"]
        assert health.json()["status"] == "unavailable"
        setting = f"SRD_MIN_FREE_DISK_MB={free_mb + 1024}"
        assert [(p["check"], p["msg"].split(" MB free on ")[1]) for p in problems] == [
            ("disk", f"the disk of the data folder (SRD_DATA_DIR), less than {setting}"),
            (
                "disk",
                f"the disk of the SQLite database's folder (SRD_DATABASE_URL), less than {setting}",
            ),
        ]
        assert not any(str(tmp_path) in p["msg"] for p in problems)
        assert client.get("/livez").status_code == 200
        assert client.post("/submit", json={}).status_code == 422  # still serving
        # No job is queued to write its artifacts there, and nothing of it is stored.
        job = {"kind": "fish", "params": {"steps": 10}}
        refused = client.post("/jobs", json=job, headers=ADMIN)
        assert refused.status_code == 503 and refused.headers["retry-after"]
        [item] = refused.json()["detail"]
        assert item["type"] == "disk_full" and "SRD_MIN_FREE_DISK_MB" in item["msg"]
        assert "the data folder (SRD_DATA_DIR)" in item["msg"]
        assert str(tmp_path) not in item["msg"]
        assert client.get("/jobs").json()["items"] == []


def test_a_sqlite_file_that_cannot_be_written_is_named_by_its_setting(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An immutable database file (which refuses even root) is not ready; the answer is public,
    so it names the setting, not the file's path."""
    monkeypatch.setattr(readiness, "CACHE_S", 0.0)
    database = Path(settings.database_url.removeprefix("sqlite:///"))
    with TestClient(create_app(settings)) as client:
        assert client.get("/healthz").status_code == 200
        if shutil.which("chattr") is None:
            pytest.skip("no chattr")
        made = subprocess.run(["chattr", "+i", str(database)], capture_output=True, check=False)
        if made.returncode != 0:
            pytest.skip(f"cannot make the file immutable: {made.stderr.decode().strip()}")
        try:
            health = client.get("/healthz")
        finally:
            subprocess.run(["chattr", "-i", str(database)], check=True)
        assert health.status_code == 503
        assert health.json()["problems"] == [
            {
                "check": "database",
                "msg": "the SQLite database (SRD_DATABASE_URL) cannot be written: its file is "
                "read-only",
            }
        ]
        assert client.get("/healthz").status_code == 200


def test_a_stalled_screener_is_not_ready(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With the screening process stopped and a submission waiting for it, ``/healthz`` names
    the screener once it has held the request ``STALL_S`` without answering; ready again
    when the process goes on and answers."""
    monkeypatch.setattr(readiness, "CACHE_S", 0.0)
    monkeypatch.setattr(pool, "STALL_S", 0.5)
    with TestClient(create_app(settings)) as client:
        assert client.post("/submit", json=honest("warm")).status_code == 201
        assert client.get("/healthz").status_code == 200
        pid = client.app.state.services.screening.pid()  # type: ignore[attr-defined]
        os.kill(pid, signal.SIGSTOP)
        try:
            with ThreadPoolExecutor(max_workers=1) as waiting:
                submitted = waiting.submit(client.post, "/submit", json=honest("waits"))
                time.sleep(1.0)
                health = client.get("/healthz")
                assert health.status_code == 503, health.text
                [problem] = health.json()["problems"]
                assert problem["check"] == "screener"
                assert "has answered no request for" in problem["msg"]
                os.kill(pid, signal.SIGCONT)
                assert submitted.result(timeout=60).status_code == 201
        finally:
            os.kill(pid, signal.SIGCONT)
        assert client.get("/healthz").status_code == 200


def test_the_answer_is_cached(settings: Settings, monkeypatch: pytest.MonkeyPatch) -> None:
    checks = 0
    real = readiness.data_dir_problem

    def counted(path: Path, what: str | None = None) -> str | None:
        nonlocal checks
        checks += 1
        return real(path, what)

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
    done = serve_once(env)
    assert done.returncode == 2
    assert done.stdout == ""
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    assert str(data_dir) in lines[0] and "SRD_DATA_DIR" in lines[0]
    said = {  # what is a file, as it is
        "file": f"the data folder {data_dir} is a file, not a folder",
        "under_a_file": f"the data folder {data_dir} cannot be made: {blocker} is a file, not a "
        "folder",
    }[where]
    assert said in lines[0], lines[0]
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "srd.db").exists()  # stopped before anything was started


@pytest.mark.parametrize(
    ("variables", "code", "words"),
    [
        ({"SRD_JOB_WORKERS": "0"}, 2, "SRD_JOB_WORKERS=0: Input should be greater than or equal"),
        ({"SRD_JOB_BACKEND": "bogus"}, 2, "SRD_JOB_BACKEND=bogus: Input should be 'local'"),
        ({"SRD_SECRETS_DIR": "/no/such"}, 2, "SRD_SECRETS_DIR=/no/such: no such folder"),
        ({"SRD_SCREENER_SECRET": "hidden-pw"}, 2, "SRD_SCREENER_SECRET: a secret has"),
        ({"SRD_ADMIN_TOKEN": "   "}, 2, "SRD_ADMIN_TOKEN: an operator token cannot be empty"),
        ({"SRD_ADMIN_TOKEN": "hidden-pw-tökén-0123456789"}, 2, "printable ASCII without white"),
        ({"SRD_REVIEW_MARGIN": "nan"}, 2, "SRD_REVIEW_MARGIN=nan: Input should be a finite number"),
        ({"SRD_JOB_BACKEND": "ray", "SRD_RAY_ADDRESS": "", "RAY_ADDRESS": ""}, 2,
         "SRD_JOB_BACKEND=ray needs SRD_RAY_ADDRESS"),
        ({"SRD_SCREENER_SECRET": "hidden-pw" * 4}, 2, "10 of them different: draw one at random"),
        ({"SRD_DATABASE_URL": "mysql://db/srd"}, 2, "SRD_DATABASE_URL names mysql"),
        ({"SRD_DATABASE_URL": "sqlite:////no-such-folder-srd/x.db"}, 3,
         "no folder /no-such-folder-srd for the SQLite database"),
        ({"SRD_DATABASE_URL": "postgresql+psycopg://u:hidden-pw@127.0.0.1:1/x"}, 3,
         "the database postgresql+psycopg://u:***@127.0.0.1:1/x (SRD_DATABASE_URL) cannot be used"),
    ],
)  # fmt: skip
def test_serve_names_the_variable_of_a_setting_it_cannot_use(
    tmp_path: Path, variables: dict[str, str], code: int, words: str
) -> None:
    """One line per problem, naming its variable, and no traceback; a secret stays unsaid."""
    env = {
        **os.environ,
        "SRD_DATA_DIR": str(tmp_path / "data"),
        "SRD_DATABASE_URL": f"sqlite:///{tmp_path / 'srd.db'}",
        "SRD_AUCTION_WORKERS": "",  # empty: the default, as compose's ${VAR:-} gives
        **variables,
    }
    done = serve_once(env)
    assert done.returncode == code, done.stderr
    assert done.stderr.splitlines() == [f"srd serve: {done.stderr[11:].strip()}"]
    assert words in done.stderr and "Traceback" not in done.stderr
    assert "hidden-pw" not in done.stderr
    assert not (tmp_path / "data").exists()  # a refused start makes nothing, its folder neither


@pytest.mark.parametrize("entry", ["empty file", "folder"])
def test_serve_refuses_a_secret_file_it_could_not_use(tmp_path: Path, entry: str) -> None:
    """An empty ``srd_admin_token`` secret file, or a folder in its place, had started a server
    with a token nobody could present, or a generated one, without a word."""
    secrets = tmp_path / "secrets"
    secrets.mkdir()
    if entry == "folder":
        (secrets / "srd_admin_token").mkdir()
    else:
        (secrets / "srd_admin_token").write_text("")
    env = {**os.environ, "SRD_DATA_DIR": str(tmp_path / "data"), "SRD_SECRETS_DIR": str(secrets),
           "SRD_DATABASE_URL": f"sqlite:///{tmp_path / 'srd.db'}"}  # fmt: skip
    env.pop("SRD_ADMIN_TOKEN", None)
    done = serve_once(env)
    assert done.returncode == 2, done.stderr
    expected = "is not a file" if entry == "folder" else "an operator token cannot be empty"
    assert expected in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "srd.db").exists()


def test_serve_refuses_an_empty_admin_token_file(tmp_path: Path) -> None:
    """An empty token file had started a server nobody could operate, without a word."""
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "admin_token").write_text("\n")
    env = {**os.environ, "SRD_DATA_DIR": str(tmp_path / "data"),
           "SRD_DATABASE_URL": f"sqlite:///{tmp_path / 'srd.db'}"}  # fmt: skip
    env.pop("SRD_ADMIN_TOKEN", None)
    done = serve_once(env)
    assert done.returncode == 2
    assert done.stderr.strip() == (
        f"srd serve: the admin token file {tmp_path / 'data' / 'admin_token'} is empty: remove "
        "it to have one made, or write one"
    )


def test_a_refused_start_removes_only_the_folders_it_made(tmp_path: Path) -> None:
    """SRD_DATA_DIR with a ``..`` in it: the start refused by the database leaves the folders
    as they were: the existing one (empty) stays, and none is made on the way."""
    (tmp_path / "data").mkdir()
    env = {**os.environ, "SRD_DATA_DIR": str(tmp_path / "missing" / ".." / "data" / "new"),
           "SRD_DATABASE_URL": "sqlite:////no-such-folder-srd/x.db"}  # fmt: skip
    done = serve_once(env)
    assert done.returncode == 3, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    assert list((tmp_path / "data").iterdir()) == []
