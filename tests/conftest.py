"""Shared fixtures for the whole suite."""

from __future__ import annotations

from pathlib import PurePath

import pytest
import torch

torch.set_num_threads(1)


@pytest.hookimpl(tryfirst=True)  # before ``-m 'not slow'`` deselects
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A test marked ``postgres_in_slow_run`` runs on PostgreSQL only in ``make test-all``: a
    feature's end-to-end test whose PostgreSQL side the storage tests already cover. The
    longest files go first (``LONGEST_FIRST``)."""
    for item in items:
        callspec = getattr(item, "callspec", None)
        on_postgres = callspec is not None and "postgresql" in callspec.params.values()
        if on_postgres and item.get_closest_marker("postgres_in_slow_run") is not None:
            item.add_marker(pytest.mark.slow)
    items.sort(key=_rank)  # stable: every worker collects the same order


LONGEST_FIRST = (
    "test_ui.py",
    "test_cli_live.py",
    "test_faults.py",
    "test_job_limits.py",
    "test_cli.py",
    "test_events.py",
    "test_remote_protocol.py",
    "test_replicas.py",
    "test_arrival.py",
    "test_cli_inputs.py",
    "test_cancel.py",
    "test_ray.py",
    "test_jobs.py",
    "test_reviews.py",
    "test_fairness.py",
    "test_readme.py",
    "test_live.py",
    "test_cheetah.py",
    "test_db_outage.py",
    "test_quotas.py",
    "test_auctions.py",
    "test_restart.py",
    "test_db.py",
    "test_readiness.py",
    "test_votes.py",
    "test_remote_e2e.py",
    "test_remote_socket.py",
    "test_enrollment.py",
    "test_lavaland.py",
)
"""The suite's longest files, longest first (each 20 s or more of servers, browsers and
deadlines, summed over its tests in a parallel run). The parallel run (``--dist loadfile
--no-loadscope-reorder``) hands files out in collection order: these go first, so that the run
does not end waiting on one of them while the other workers idle. (By default pytest-xdist
orders the files by their number of tests instead: the long files of few tests, kill -9 and
outage scenarios, went last, and the run ended on them.)"""


def _rank(item: pytest.Item) -> int:
    """Where a test's file goes in the run: ``LONGEST_FIRST`` first, the others after, in
    their order."""
    name = PurePath(str(item.path)).name
    return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)
