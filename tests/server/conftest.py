"""Server fixtures: a throw-away database per backend (SQLite file, real PostgreSQL) and the app
in-process. Helpers and factories live in ``tests/support``."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from server.app import create_app
from server.config import Settings
from tests.support.databases import BACKENDS, fresh_database
from tests.support.server import make_settings


@pytest.fixture(scope="module", params=BACKENDS)
def database_url(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[str]:
    """A fresh empty database for the module: a SQLite file, or a new PostgreSQL database
    dropped afterwards."""
    yield from fresh_database(request.param, tmp_path_factory.mktemp("db"))


@pytest.fixture(params=BACKENDS)
def fresh_database_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh empty database for one test (for tests that kill and restart servers on it)."""
    yield from fresh_database(request.param, tmp_path)


@pytest.fixture(scope="module")
def settings(database_url: str, tmp_path_factory: pytest.TempPathFactory) -> Settings:
    return make_settings(database_url, tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="module")
def client(settings: Settings) -> Iterator[TestClient]:
    """The app in-process, lifespan included (migrations, worker pools)."""
    with TestClient(create_app(settings)) as test_client:
        yield test_client
