"""What a worker process costs to start: the fork server against a fresh interpreter.

The server's worker pools and its screening process start their children with
``server.work.pool.process_context()``: forked from a fork server that imported torch, the
screener and the task modules once. This benchmark starts ``--runs`` children each way, one
after another, each running a worker's first lines (import torch, the task modules), and prints
for each way the wall time from ``start()`` to the child running, and the CPU time the child
used until then (measured in the child). The fork server's own start (its one-time import) is
printed apart.

Run: ``.venv/bin/python benchmarks/worker_start.py [--runs 5]``
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import sys
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the packages, not benchmarks/*
from server.work.pool import process_context


def _child(conn: Connection) -> None:
    """A worker's first lines: the imports its tasks need; then report its own CPU time."""
    import torch  # noqa: F401

    import screener  # noqa: F401
    import server.auctions.steps
    import server.jobs.worker  # noqa: F401

    conn.send((time.monotonic(), time.process_time()))
    conn.recv()  # wait to be told to end


def _start(context: Any) -> tuple[float, float]:
    """Wall seconds from start() to the child's imports done, and the child's CPU seconds."""
    ours, theirs = multiprocessing.Pipe()
    process = context.Process(target=_child, args=(theirs,))
    began = time.monotonic()
    process.start()
    if not ours.poll(300):
        raise SystemExit(f"the child did not start (exit code {process.exitcode})")
    up_at, cpu = ours.recv()
    ours.send(None)
    process.join()
    return up_at - began, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    runs = parser.parse_args().runs
    forked = process_context()
    first_wall, _ = _start(forked)  # starts the fork server: its import, once
    print(f"fork server's first child (its own import included): {first_wall:.2f} s wall")
    ways = {"fork server": forked, "spawn": multiprocessing.get_context("spawn")}
    print(f"{'start method':>12} {'wall to ready, median':>22} {'child CPU, median':>18}")
    for name, context in ways.items():
        timings = [_start(context) for _ in range(runs)]
        wall = statistics.median(t[0] for t in timings)
        cpu = statistics.median(t[1] for t in timings)
        print(f"{name:>12} {wall * 1e3:19.1f} ms {cpu * 1e3:15.1f} ms")


if __name__ == "__main__":
    main()
