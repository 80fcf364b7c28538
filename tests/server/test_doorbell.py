"""Doorbells between the API and its workers (``server.doorbell``)."""

from __future__ import annotations

import multiprocessing
import secrets
import sys

import pytest

from server import doorbell

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="bells use Linux's abstract sockets"
)


def _scope() -> str:
    return doorbell.scope(f"sqlite:///{secrets.token_hex(8)}.db")


def _ring_from_child(scope: str, name: str) -> None:
    doorbell.ring(scope, name)


def test_a_ring_wakes_the_listener_and_is_taken_once() -> None:
    scope = _scope()
    with doorbell.listen(scope, doorbell.round_bell(7)) as bell:
        assert bell is not None
        assert bell.wait(0.0) is False
        doorbell.ring(scope, doorbell.round_bell(7))
        doorbell.ring(scope, doorbell.round_bell(7))
        assert bell.wait(5.0) is True
        assert bell.wait(0.0) is False, "both rings were taken by the first wait"


def test_a_ring_from_another_process_wakes_the_listener() -> None:
    scope = _scope()
    bell = doorbell.listen(scope, doorbell.watch_bell(12345))
    assert bell is not None
    try:
        child = multiprocessing.get_context("spawn").Process(
            target=_ring_from_child, args=(scope, doorbell.watch_bell(12345))
        )
        child.start()
        child.join(60)
        assert child.exitcode == 0
        assert bell.wait(5.0) is True
    finally:
        bell.close()


def test_bells_are_scoped_by_database_and_name() -> None:
    scope, other = _scope(), _scope()
    assert doorbell.scope("sqlite:///a.db") == doorbell.scope("sqlite:///a.db") != scope
    with doorbell.listen(scope, doorbell.round_bell(1)) as bell:
        assert bell is not None
        doorbell.ring(other, doorbell.round_bell(1))  # another deployment
        doorbell.ring(scope, doorbell.round_bell(2))  # another round
        assert bell.wait(0.05) is False


def test_one_listener_per_bell_and_ringing_nobody_is_harmless() -> None:
    scope = _scope()
    doorbell.ring(scope, doorbell.round_bell(3))  # nobody listens: no error
    first = doorbell.listen(scope, doorbell.round_bell(3))
    assert first is not None
    try:
        assert doorbell.listen(scope, doorbell.round_bell(3)) is None  # the caller polls
    finally:
        first.close()
    again = doorbell.listen(scope, doorbell.round_bell(3))  # freed with its socket
    assert again is not None
    again.close()
