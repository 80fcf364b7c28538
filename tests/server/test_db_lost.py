"""Loud failures: a database deleted or replaced under a running server turns /healthz to 503
and refuses reads and writes, for good; a server never starts over a lost database with an
empty one."""

from __future__ import annotations

import shutil
import time

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import Engine, create_engine, text

from server.api import readiness
from server.app import create_app
from server.store import db
from server.store.db import DatabaseUnavailableError, upgrade_schema
from tests.support.databases import postgres_database
from tests.support.factories import honest, unique
from tests.support.server import ADMIN, make_settings


@pytest.fixture(autouse=True)
def quick_checks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(db, "IDENTITY_CHECK_S", 0.0)  # check on every call
    monkeypatch.setattr(readiness, "CACHE_S", 0.0)


def test_deleted_sqlite_file_is_noticed_and_never_recreated(tmp_path) -> None:
    path = tmp_path / "srd.db"
    settings = make_settings(f"sqlite:///{path}", tmp_path / "data")
    with TestClient(create_app(settings)) as client:
        assert client.get("/healthz").status_code == 200
        assert client.post("/submit", json=honest(unique("before"))).status_code == 201
        for suffix in ("", "-wal", "-shm"):
            path.with_name(path.name + suffix).unlink(missing_ok=True)
        health = client.get("/healthz")
        assert health.status_code == 503 and health.json()["status"] == "unavailable"
        assert health.json()["problems"][0]["check"] == "database"
        assert "deleted" in health.json()["problems"][0]["msg"]
        assert client.post("/submit", json=honest(unique("after"))).status_code == 503
        read = client.get("/models/1")  # the deleted file is still open: no stale answer
        assert read.status_code == 503 and read.json()["detail"][0]["loc"] == ["database"]
        time.sleep(0.05)
        assert client.get("/healthz").status_code == 503  # for good: no check clears it
        refused = client.post("/auctions", json={"n_fish": 1}, headers=ADMIN)
        assert refused.status_code == 503
        assert refused.json()["detail"][0]["loc"] == ["database"]
        assert client.post("/jobs", json={"kind": "fish"}, headers=ADMIN).status_code == 503
    assert not path.exists()  # nothing made a new empty database
    with (
        pytest.raises(DatabaseUnavailableError, match="deleted or replaced"),
        TestClient(create_app(settings)),
    ):
        pass
    assert not path.exists()
    settings.databases_file.unlink()  # the operator's explicit choice: start anew
    with TestClient(create_app(settings)) as client:
        assert client.get("/healthz").status_code == 200


def test_replaced_sqlite_file_is_noticed(tmp_path) -> None:
    path, other = tmp_path / "srd.db", tmp_path / "other.db"
    upgrade_schema(f"sqlite:///{other}")
    settings = make_settings(f"sqlite:///{path}", tmp_path / "data")
    with TestClient(create_app(settings)) as client:
        assert client.get("/healthz").status_code == 200
        shutil.move(other, path)
        time.sleep(0.01)
        health = client.get("/healthz")
        assert health.status_code == 503 and "replaced" in health.json()["problems"][0]["msg"]
        assert client.post("/submit", json=honest(unique("swap"))).status_code == 503


@pytest.mark.postgres
def test_dropped_postgres_database_is_noticed(tmp_path) -> None:
    for url in postgres_database():
        settings = make_settings(url, tmp_path / "data")
        with TestClient(create_app(settings)) as client:
            assert client.get("/healthz").status_code == 200
            name = url.rsplit("/", 1)[1]
            admin = create_engine(url.rsplit("/", 1)[0] + "/postgres", isolation_level="AUTOCOMMIT")
            with admin.connect() as connection:
                connection.execute(text(f'DROP DATABASE "{name}" WITH (FORCE)'))
                connection.execute(text(f'CREATE DATABASE "{name}"'))
            admin.dispose()
            health = client.get("/healthz")
            assert health.status_code == 503
            assert client.post("/submit", json=honest(unique("pg"))).status_code == 503
        with (
            pytest.raises(DatabaseUnavailableError, match="deleted or replaced"),
            TestClient(create_app(settings)),
        ):
            pass


def read_only(admin: Engine, name: str, on: bool) -> None:
    """Make the database ``name`` read-only (or not) for new transactions, and end its
    connections so that every new one takes the setting."""
    with admin.connect() as connection:
        value = "on" if on else "off"
        connection.execute(
            text(f'ALTER DATABASE "{name}" SET default_transaction_read_only = {value}')
        )
        connection.execute(
            text(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                "WHERE datname = :name AND pid <> pg_backend_pid()"
            ),
            {"name": name},
        )


def test_a_read_only_postgres_database_refuses_writes_with_the_json_503(tmp_path) -> None:
    """A database that turned read-only (a standby promoted away, or the setting flipped) is an
    outage for writes: each gets the JSON 503 naming the database, reads go on, and writes come
    back by themselves once it takes them again."""
    for url in postgres_database():
        settings = make_settings(url, tmp_path / "data")
        name = url.rsplit("/", 1)[1]
        admin = create_engine(url.rsplit("/", 1)[0] + "/postgres", isolation_level="AUTOCOMMIT")

        try:
            with TestClient(create_app(settings)) as client:
                submitted = client.post("/submit", json=honest(unique("ro")))
                assert submitted.status_code == 201, submitted.text
                read_only(admin, name, True)
                body = {"n_fish": 1, "model_ids": [submitted.json()["model_id"]]}
                refused = None
                for _ in range(20):  # the first statement on a terminated connection reconnects
                    refused = client.post("/auctions", json=body, headers=ADMIN)
                    if refused.status_code == 503:
                        break
                assert refused is not None and refused.status_code == 503, refused.text
                assert refused.headers["content-type"] == "application/json"
                (item,) = refused.json()["detail"]
                assert item["loc"] == ["database"] and "read-only" in item["msg"]
                assert client.get(f"/models/{submitted.json()['model_id']}").status_code == 200
                read_only(admin, name, False)
                for _ in range(20):
                    created = client.post("/auctions", json=body, headers=ADMIN)
                    if created.status_code == 201:
                        break
                assert created.status_code == 201, created.text
        finally:
            read_only(admin, name, False)
            admin.dispose()
