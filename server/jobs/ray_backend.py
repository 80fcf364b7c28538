"""Job units on a Ray cluster (``SRD_JOB_BACKEND=ray``).

A job still runs in its own worker process on the API's machine (claim, progress, artifacts,
result, time and memory limits, cancellation: ``server.jobs.worker``); only its units
(``sim.units``) are computed elsewhere, as Ray tasks. The worker connects to the cluster as a
Ray driver, submits every unit at once and waits for them in completion order (``ray.wait``),
so the job's progress moves as each unit ends. A task receives the job's kind, its JSON params
and the unit's JSON spec and returns the unit's payload (JSON values and numpy arrays): no
Python object of ours crosses the wire, and the assembled result is the local backend's.

* A unit lost with its worker process or node runs again, up to ``SRD_RAY_MAX_RETRIES``
  times (units are idempotent); an exception raised by the unit's own code fails the job.
* Cancelling the job terminates its worker process; SIGTERM in the driver raises
  ``SystemExit`` (``_stopped``, in place of Ray's handler), and on the way out the worker
  cancels every unfinished task (force: their Ray workers are stopped), so the cluster stops
  working on a cancelled job at once. The worker then exits 128 + SIGTERM, as a process the
  signal ended says to a shell: a worker stopped from outside (a service manager stopping the
  service) is counted as stopped, and its job runs again, as on the local backend (Ray's
  handler exited 1 or 15: the job failed).
* A cluster lost mid-job fails the job naming it: Ray's own errors for a lost node or raylet
  (``LOST``) are said as the cluster lost, and a driver that Ray itself ends (it exits with
  code 1 once its raylet is gone) has its death explained by ``cluster_lost``: the cluster
  lost when its head does not answer, else this machine's Ray node.
* Tasks ask for one CPU each, a unit of a job with a ``threads`` option (cheetah: MuJoCo
  stepped in parallel) for that many, and set torch's thread count to the job workers' own
  (``SRD_WORKER_TORCH_THREADS``), so their floating-point arithmetic is the local one.

Ray is an optional extra: ``pip install '.[ray]'``.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from functools import cache
from typing import Any

from server.config import JobBackendName
from sim.experiment import config_dict
from sim.units import Payload, Unit, UnitProgress
from studies.registry import compute_unit

log = logging.getLogger("srd.ray")

INSTALL_HINT = "pip install '.[ray]'  (or: pip install 'srd-auction[ray]')"
"""How to get Ray, as every error about its absence says."""
WAIT_S = 0.5
"""Longest single ``ray.wait``: the driver's signal handlers (cancellation) run between waits."""
PROBE_EVERY_S = 30.0
"""How long the cluster's CPU count is trusted before ``/healthz`` has it looked at again."""
NAMESPACE = "srd-auction"
"""The Ray namespace of every driver of this service."""
CLUSTER_LOOK_S = 2.0
"""How long ``cluster_lost`` waits for the head to take a connection, and between its looks."""


LOST = ("LocalRayletDiedError", "NodeDiedError", "RaySystemError")
"""Ray's errors that say the cluster, not the unit's own code, failed the wait for a unit."""


class RayUnavailableError(RuntimeError):
    """Ray is asked for but missing, or its cluster cannot be reached."""


def cluster_lost(address: str | None) -> str:
    """Why a job worker (a Ray driver) ended with code 1 and no result: Ray ends a driver so
    once its node's raylet is gone, with the cluster or alone. Said as the cluster lost when its
    head at ``address`` does not answer now (looked at twice, ``CLUSTER_LOOK_S`` apart: a
    cluster being stopped loses its raylets before its head)."""
    address = _required(address)
    for look in range(2):
        try:
            head_answers(address, CLUSTER_LOOK_S)
        except RayUnavailableError as exc:
            return f"its Ray cluster was lost: {exc}"
        if look == 0:
            time.sleep(CLUSTER_LOOK_S)
    return (
        "Ray ends a driver so when the Ray node on this machine is lost (the cluster's head at "
        f"{address!r}, SRD_RAY_ADDRESS, answers)"
    )


def ray_module() -> Any:
    """The ``ray`` package, or RayUnavailableError saying how to install it."""
    # Read when Ray is imported: without it Ray's core worker prints a stack dump for the
    # SIGTERM that cancels a job's worker (SIGTERM still raises SystemExit in the driver).
    os.environ.setdefault("RAY_DISABLE_FAILURE_SIGNAL_HANDLER", "1")
    try:
        return importlib.import_module("ray")
    except ImportError as exc:
        raise RayUnavailableError(
            f"SRD_JOB_BACKEND=ray needs Ray, which is not installed: {INSTALL_HINT}"
        ) from exc


def _required(address: str | None) -> str:
    """The cluster's address, or RayUnavailableError naming the setting."""
    if not address:
        raise RayUnavailableError(
            "SRD_JOB_BACKEND=ray needs the cluster's address: set SRD_RAY_ADDRESS (or Ray's "
            "own RAY_ADDRESS) to the head's host:port, ray://host:port, or auto"
        )
    return address


def head_answers(address: str, timeout_s: float) -> None:
    """RayUnavailableError unless the head at ``address`` (``host:port``, or ``ray://host:port``)
    takes a TCP connection within ``timeout_s``: ``ray.init`` retries an address nobody answers
    on for minutes, and a job would wait in ``running`` meanwhile. Other forms (``auto``) are
    Ray's to resolve."""
    host, colon, port = address.removeprefix("ray://").rpartition(":")
    if not colon or not port.isdigit():
        return
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except OSError as exc:
        raise RayUnavailableError(
            f"cannot join the Ray cluster at {address!r} (SRD_RAY_ADDRESS): {exc}"
        ) from exc


def connect(address: str | None, timeout_s: float) -> Any:
    """Join the Ray cluster at ``address`` as a driver (once per process); returns ``ray``.
    A head that does not answer within ``timeout_s`` is RayUnavailableError: one that refuses
    the connection at once; one that takes it and never answers (a frozen head) when a child
    process's join (``probe_cpus``) gives up, since ``ray.init`` itself waits for ever and no
    signal interrupts it."""
    address = _required(address)
    ray = ray_module()
    if not ray.is_initialized():
        probe_cpus(address, timeout_s)
        try:
            ray.init(
                address=address,
                namespace=NAMESPACE,
                log_to_driver=False,
                logging_level=logging.WARNING,
            )
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise RayUnavailableError(
                f"cannot join the Ray cluster at {address!r} (SRD_RAY_ADDRESS): {exc}"
            ) from exc
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, _stopped)
    return ray


_stopped_by: list[int] = []
"""The signal that stopped this driver, if one did (``_stopped``)."""


def _stopped(signum: int, frame: object) -> None:
    """SIGTERM in a job worker that is a Ray driver (module docstring). Raised inside a Ray
    call, the exit becomes Ray's ``SystemExit(1)``: the waits' ``finally`` says it again."""
    _stopped_by.append(signum)
    raise SystemExit(128 + signum)


def unit_task(kind: str, params: dict[str, Any], unit: dict[str, Any], threads: int) -> Payload:
    """The body of one unit's Ray task: the job workers' torch thread count, then the unit."""
    import torch

    torch.set_num_threads(threads)
    return compute_unit(kind, params, unit)


@cache
def _remote_unit_task() -> Any:
    """``unit_task`` as a Ray remote function (made once per process, after ``connect``)."""
    return ray_module().remote(num_cpus=1)(unit_task)


class RayRunner:
    """Computes a job's units as Ray tasks (a ``sim.units.UnitRunner``): every unit submitted
    at once, their payloads yielded as they finish."""

    def __init__(
        self,
        kind: str,
        config: Any,
        *,
        address: str | None,
        join_timeout_s: float,
        max_retries: int,
        threads: int,
    ) -> None:
        self._ray = connect(address, join_timeout_s)
        self._address = address
        self._kind = kind
        self._params = config_dict(config)
        self._max_retries = max_retries
        self._threads = threads
        self._cpus = int(getattr(config, "threads", 1))  # what one unit keeps busy

    def __call__(
        self, units: Sequence[Unit], progress: UnitProgress
    ) -> Iterator[tuple[int, Payload]]:
        ray = self._ray
        # A task asking for more CPUs than any node has waits for ever: a unit keeps at most
        # the largest node's CPUs busy (its numbers do not depend on its threads).
        largest = max(
            (n["Resources"].get("CPU", 0.0) for n in ray.nodes() if n.get("Alive")), default=0.0
        )
        if largest < 1:
            raise RayUnavailableError("the Ray cluster has no CPU to compute units on")
        cpus = min(self._cpus, int(largest))
        if cpus < self._cpus:
            log.info("%s: threads %d > the largest node's %d CPUs", self._kind, self._cpus, cpus)
        task = _remote_unit_task()
        params = ray.put(self._params)
        refs = {
            task.options(
                num_cpus=cpus,
                max_retries=self._max_retries,
                retry_exceptions=False,
                name=f"srd {self._kind}: {unit.label}",
            ).remote(self._kind, params, unit.as_json(), self._threads): index
            for index, unit in enumerate(units)
        }
        pending = list(refs)
        started = time.monotonic()
        try:
            while pending:
                try:
                    ready, pending = ray.wait(pending, num_returns=1, timeout=WAIT_S)
                    done = [(refs[ref], ray.get(ref)) for ref in ready]
                except ray.exceptions.RayError as exc:
                    first = (str(exc).splitlines() or [""])[0]
                    if type(exc).__name__ == "WorkerCrashedError":  # every try it had
                        tries = self._max_retries + 1
                        raise RuntimeError(
                            f"a unit's Ray worker died {tries} time{'s' if tries > 1 else ''}, "
                            f"every try it had (SRD_RAY_MAX_RETRIES={self._max_retries}): "
                            f"{first}"
                        ) from exc
                    if type(exc).__name__ not in LOST:
                        raise  # the unit's own error
                    raise RayUnavailableError(
                        f"the Ray cluster at {self._address!r} (SRD_RAY_ADDRESS) was lost "
                        f"mid-job: {type(exc).__name__}: {first}"
                    ) from exc
                yield from done
        finally:
            for ref in pending:  # cancelled, failed, or the process is stopping
                ray.cancel(ref, force=True)
            log.info("%d units of %s in %.1f s", len(refs), self._kind, time.monotonic() - started)
            if _stopped_by:
                raise SystemExit(128 + _stopped_by[0])  # the stop's own code


_PROBE = """
import json, logging, os, signal, sys
if sys.platform.startswith("linux"):  # ends with the thread that started it (a job worker
    import ctypes  # killed by a cancel while the head hangs, say), before joining
    ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != int(sys.argv[3]):  # that thread already gone
        sys.exit(1)
import ray
ray.init(address=sys.argv[1], namespace=sys.argv[2], log_to_driver=False,
         logging_level=logging.ERROR)
print(json.dumps(ray.cluster_resources().get("CPU", 0.0)))
"""
"""A child process's look at the cluster: it joins, prints the CPUs and leaves; it is killed
when the process that started it dies (its own wait for a frozen head would outlive it)."""


def probe_cpus(address: str, timeout_s: float) -> float:
    """The CPUs of the cluster at ``address``, read by a child process that joins it as a
    driver and leaves; RayUnavailableError with the reason when it cannot within
    ``timeout_s`` (a head that refuses the connection: at once). The server itself never joins:
    Ray ends a driver whose cluster has been gone for a minute, and waits forever for an
    address nobody answers on."""
    head_answers(address, timeout_s)
    try:
        done = subprocess.run(
            [sys.executable, "-c", _PROBE, address, NAMESPACE, str(os.getpid())],
            capture_output=True,
            text=True,
            timeout=timeout_s,
            check=False,
        )
    except subprocess.TimeoutExpired as exc:
        raise RayUnavailableError(
            f"cannot join the Ray cluster at {address!r} (SRD_RAY_ADDRESS): no answer within "
            f"{timeout_s:g} s (SRD_RAY_JOIN_TIMEOUT_S)"
        ) from exc
    lines = done.stdout.strip().splitlines()
    if done.returncode != 0 or not lines:
        said = [line for line in done.stderr.strip().splitlines() if line.strip()]
        raise RayUnavailableError(
            f"cannot join the Ray cluster at {address!r} (SRD_RAY_ADDRESS): "
            f"{said[-1] if said else f'the probe exited with code {done.returncode}'}"
        )
    return float(lines[-1])


class RayCluster:
    """The API process's view of the cluster, through ``probe_cpus``: looked at once at start
    (so a wrong address or a missing Ray stops the server with the reason), then again at most
    every ``PROBE_EVERY_S`` in the background while ``/healthz`` is asked; 0 CPUs while the
    cluster cannot be reached (its jobs fail; the API serves on)."""

    name: JobBackendName = "ray"

    def __init__(self, address: str | None, timeout_s: float) -> None:
        self._address = _required(address)
        if importlib.util.find_spec("ray") is None:
            ray_module()  # raises with the fix
        self._timeout_s = timeout_s
        self._cpus = probe_cpus(self._address, timeout_s)
        self._asked_at = time.monotonic()
        self._probing = threading.Lock()

    def cpus(self) -> float:
        """The CPUs of every node alive in the cluster, as last seen (the look is renewed in
        the background once it is older than ``PROBE_EVERY_S``)."""
        if time.monotonic() - self._asked_at > PROBE_EVERY_S and self._probing.acquire(False):
            self._asked_at = time.monotonic()
            threading.Thread(target=self._probe, name="srd-ray-probe", daemon=True).start()
        return self._cpus

    def _probe(self) -> None:
        try:
            self._cpus = probe_cpus(self._address, self._timeout_s)
        except RayUnavailableError as exc:
            if self._cpus:
                log.warning("the Ray cluster cannot be reached: %s", exc)
            self._cpus = 0.0
        finally:
            self._probing.release()

    def close(self) -> None:
        """Nothing to let go of: this process never joined the cluster."""
