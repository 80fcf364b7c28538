"""Real ``srd serve`` processes for the crash, restart and replica tests and for the starts it
refuses, and what Linux's ``/proc`` says of them (their children, their CPU time) for those
tests and the benchmarks."""

from __future__ import annotations

import errno
import multiprocessing
import os
import secrets
import subprocess
from pathlib import Path

import pytest

from server.cli.launch import ServerProcess, free_port, srd_command


def serve_once(env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """``srd serve`` on a free port with ``env``, run to its exit (a start it refuses): its code,
    stdout and stderr."""
    return subprocess.run(
        [*srd_command(), "serve", "--port", str(free_port())],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def server_pair(
    database_url: str, folder: Path, extra_env: dict[str, str] | None = None
) -> tuple[tuple[ServerProcess, ServerProcess], dict[str, str]]:
    """Two servers on one database and one data folder with one fresh operator token (not
    started): a restart's first and second life, or two replicas. Also the admin header."""
    token = secrets.token_hex(16)
    a, b = (
        ServerProcess(
            database_url=database_url,
            data_dir=folder / "data",
            admin_token=token,
            extra_env=extra_env,
            log_path=folder / f"serve-{name}.log",
        )
        for name in ("a", "b")
    )
    return (a, b), {"Authorization": f"Bearer {token}"}


def _stat(pid: int | str) -> list[str]:
    """The fields of ``/proc/<pid>/stat`` after the command name (state first); raises
    OSError for a process that is gone."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def _parents() -> dict[int, int]:
    """Every live process and its parent, from one scan of ``/proc``."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int(_stat(entry.name)[1])
            except OSError:
                continue
    return parents


def children(pid: int) -> list[int]:
    """Direct children of ``pid``."""
    return [child for child, parent in _parents().items() if parent == pid]


def descendants(pid: int) -> list[int]:
    """``pid`` and every live process below it (one scan of ``/proc``)."""
    parents = _parents()
    tree, frontier = [pid], [pid]
    while frontier:
        up = frontier.pop()
        below = [child for child, parent in parents.items() if parent == up]
        tree += below
        frontier += below
    return tree


def cpu_seconds(pid: int | str) -> float | None:
    """User + system CPU seconds a process (or ``"<pid>/task/<tid>"``, one of its threads) has
    used so far; None once it is gone."""
    try:
        fields = _stat(pid)
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def process_name(pid: int) -> str | None:
    """The process's name (``/proc/<pid>/comm``, at most 15 characters); None once it is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split("(", 1)[1].rsplit(")", 1)[0]
    except OSError:
        return None


def reaped_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of the children ``pid`` has waited for (ended workers)."""
    try:
        fields = _stat(pid)
    except OSError:
        return None
    return (int(fields[13]) + int(fields[14])) / os.sysconf("SC_CLK_TCK")


def refuse_starts(monkeypatch: pytest.MonkeyPatch, name: str, times: int) -> list[OSError]:
    """Make the system refuse to start the next ``times`` processes named ``name`` (EAGAIN, as
    a process limit does; ``multiprocessing``'s start raises it); the refusals still to come,
    emptied as they are made."""
    refusals = [OSError(errno.EAGAIN, "Resource temporarily unavailable")] * times
    start = multiprocessing.process.BaseProcess.start

    def refusing(process: multiprocessing.process.BaseProcess) -> None:
        if process.name == name and refusals:
            raise refusals.pop()
        start(process)

    monkeypatch.setattr(multiprocessing.process.BaseProcess, "start", refusing)
    return refusals
