"""Shared fixtures for the whole suite."""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)


@pytest.hookimpl(tryfirst=True)  # before ``-m 'not slow'`` deselects
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A test marked ``postgres_in_slow_run`` runs on PostgreSQL only in ``make test-all``: a
    feature's end-to-end test whose PostgreSQL side the storage tests already cover."""
    for item in items:
        callspec = getattr(item, "callspec", None)
        on_postgres = callspec is not None and "postgresql" in callspec.params.values()
        if on_postgres and item.get_closest_marker("postgres_in_slow_run") is not None:
            item.add_marker(pytest.mark.slow)
