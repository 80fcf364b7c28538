"""The in-process server of the tests: its settings and token, polling, and what a test reads
back (error locations, row counts)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.cli.launch import ServerProcess
from server.config import Settings

ADMIN_TOKEN = "test-admin-token-0123456789abcdef"
ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
QUOTAS_OFF = {
    "quota_versions_per_minute": 10**6,
    "quota_versions_per_day": 10**6,
    "quota_address_versions_per_minute": 10**6,
    "quota_address_versions_per_day": 10**6,
    "quota_registrations_per_day": 10**6,
    "quota_address_refusals_per_hour": 10**6,
    "refusal_cooldown_s": 0.0,
    "limit_address_requests_per_s": 1e9,
}
"""Settings that lift the submission quotas and the request rate per address: for tests and
benchmarks that submit many models, or send many requests, from one address
(``tests/server/test_quotas.py`` and ``test_fairness.py`` test them)."""


def make_settings(database_url: str, data_dir: Path, **overrides: Any) -> Settings:
    """Test settings: fixed admin token, fast progress writes, quotas off, review off (a
    test of the review queue sets ``review_margin``)."""
    values: dict[str, Any] = {
        "review_margin": 0.0,
        "database_url": database_url,
        "data_dir": data_dir,
        "admin_token": ADMIN_TOKEN,
        "progress_interval_s": 0.1,
        "job_workers": 2,
        "auction_workers": 2,
        **QUOTAS_OFF,
    }
    values.update(overrides)
    return Settings(**values)


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


def locs(response: Any) -> list[list[Any]]:
    """The ``loc`` of every error entry (and check the common error body on the way)."""
    body = response.json()
    assert set(body) == {"detail"}
    for item in body["detail"]:
        assert set(item) == {"loc", "msg", "type"} and isinstance(item["msg"], str)
    return [item["loc"] for item in body["detail"]]


def count(client: TestClient, table: Any, **where: Any) -> int:
    """Rows of ``table`` (a model class) matching ``where``, read through the app's database."""
    database = client.app.state.services.database  # type: ignore[attr-defined]
    with database.session(write=False) as session:
        query = select(func.count()).select_from(table)
        for column, value in where.items():
            query = query.where(getattr(table, column) == value)
        return int(session.scalar(query) or 0)


def module_server(
    tmp_path_factory: pytest.TempPathFactory, name: str, env: dict[str, str] | None = None
) -> Iterator[ServerProcess]:
    """A real ``srd serve`` on a fresh SQLite database with the test operator token (and the
    settings ``env`` gives), for a module's tests (yield it from a module-scoped fixture)."""
    data_dir = tmp_path_factory.mktemp(name)
    with ServerProcess(
        database_url=f"sqlite:///{data_dir / 'srd.db'}",
        data_dir=data_dir,
        admin_token=ADMIN_TOKEN,
        extra_env=env,
    ) as running:
        yield running
