"""Shared fixtures for the whole suite."""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)


LONGEST_FILES = (
    "tests/server/test_ui.py",
    "tests/server/test_faults.py",
    "tests/server/test_replicas.py",
    "tests/server/test_cli.py",
    "tests/server/test_remote_e2e.py",
    "tests/server/test_cli_live.py",
    "tests/server/test_votes.py",
    "tests/server/test_fairness.py",
    "tests/server/test_workers.py",
    "tests/server/test_events.py",
)
"""The test files that take longest (35-80 s each on two cores), run first: ``make test``'s
processes take whole files in collection order, so one of these left for last kept one process
busy while the others idled (``--junitxml`` gives each test's time)."""


@pytest.hookimpl(tryfirst=True)  # before ``-m 'not slow'`` deselects
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The longest files first (``LONGEST_FILES``). A test marked ``postgres_in_slow_run`` runs
    on PostgreSQL only in ``make test-all``: a feature's end-to-end test whose PostgreSQL side
    the storage tests already cover."""
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))
    for item in items:
        callspec = getattr(item, "callspec", None)
        on_postgres = callspec is not None and "postgresql" in callspec.params.values()
        if on_postgres and item.get_closest_marker("postgres_in_slow_run") is not None:
            item.add_marker(pytest.mark.slow)
