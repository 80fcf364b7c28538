"""Server fixtures: a throw-away database per backend (SQLite file, real PostgreSQL), an
in-process app client, and manifest factories."""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from agents.negotiator import honest_manifest, saboteur_manifest
from server.app import create_app
from server.config import Settings
from server.launch import LOCAL_POSTGRES, QUOTAS_OFF, postgres_admin_url, throwaway_postgres

ADMIN_TOKEN = "test-admin-token-0123456789abcdef"
ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def _throwaway_pg_database() -> Iterator[str]:
    admin_url = postgres_admin_url()
    if admin_url is None:
        pytest.skip(f"PostgreSQL unreachable on {LOCAL_POSTGRES}; .ci/run starts it")
    with throwaway_postgres(admin_url) as url:
        yield url


@pytest.fixture(
    scope="module",
    params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)],
)
def database_url(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[str]:
    """A fresh empty database: a SQLite file, or a new PostgreSQL database dropped afterwards."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path_factory.mktemp('db') / 'srd.db'}"
    else:
        yield from _throwaway_pg_database()


UNLIMITED = QUOTAS_OFF
"""Quotas out of the way of tests that submit many models from one address (test_quotas.py
tests them)."""


def make_settings(database_url: str, data_dir: Path, **overrides: Any) -> Settings:
    """Test settings: fixed admin token, fast progress writes."""
    values: dict[str, Any] = {
        "database_url": database_url,
        "data_dir": data_dir,
        "admin_token": ADMIN_TOKEN,
        "progress_interval_s": 0.1,
        "job_workers": 2,
        "auction_workers": 2,
        **UNLIMITED,
    }
    values.update(overrides)
    return Settings(**values)


@pytest.fixture(scope="module")
def settings(database_url: str, tmp_path_factory: pytest.TempPathFactory) -> Settings:
    return make_settings(database_url, tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="module")
def client(settings: Settings) -> Iterator[TestClient]:
    """The app in-process, lifespan included (migrations, worker pools)."""
    with TestClient(create_app(settings)) as test_client:
        yield test_client


def unique(prefix: str) -> str:
    """A participant name no other test uses."""
    return f"{prefix}-{uuid.uuid4().hex[:10]}"


def honest(name: str, seed: int = 0) -> dict[str, Any]:
    """An honest FSN manifest as JSON."""
    return honest_manifest(np.random.default_rng(seed), name).model_dump(mode="json")


def saboteur(name: str, seed: int = 0) -> dict[str, Any]:
    """An always-hold saboteur manifest as JSON."""
    return saboteur_manifest(np.random.default_rng(seed), name).model_dump(mode="json")


def wait_for(
    fetch: Callable[[], dict[str, Any]], done: Callable[[dict[str, Any]], bool], timeout_s: float
) -> dict[str, Any]:
    """Poll ``fetch`` until ``done`` holds; fail the test with the last state on timeout."""
    deadline = time.monotonic() + timeout_s
    state = fetch()
    while not done(state):
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s; last state: {state}")
        time.sleep(0.1)
        state = fetch()
    return state
