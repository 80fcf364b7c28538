"""Worker processes: auctions and jobs run in child processes, off the API's event loop and GIL.

``WorkerPool`` keeps a FIFO of task ids and at most ``max_workers`` worker processes, forked
from a fork server that has imported torch and the task modules once (``process_context``: a
clean import state, no inherited locks, sockets or database connections). A supervisor
thread hands queued task ids to idle workers over pipes, notices finished tasks and dead
processes, and reports a task whose process died under it to ``on_exit`` (unless the task was
cancelled or the pool is stopping). Children die with the API process (on Linux the kernel
kills the fork server and then its children, ``PR_SET_PDEATHSIG``; a watchdog on the parent pid
everywhere), so a killed server leaves no orphan writing to the database.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import logging
import math
import multiprocessing
import os
import resource
import signal
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from multiprocessing.context import ForkServerContext, SpawnContext

log = logging.getLogger("srd.workers")

SUPERVISOR_TICK_S = 0.5  # the supervisor also wakes on every submission and task end
TERMINATE_GRACE_S = 3.0  # SIGTERM, then SIGKILL after this long
PARENT_WATCH_S = 0.5  # how often a child checks that its parent is alive
ERROR_LIMIT = 4000  # characters of a traceback summary kept in the database
PR_SET_PDEATHSIG = 1  # prctl option: signal to receive when the parent dies
STARTED, DONE = "started", "done"  # what a worker says about its task, over its pipe
PR_SET_NAME = 15  # prctl option: the thread's name in /proc (ps, top), at most 15 bytes


@dataclass(frozen=True)
class WorkerContext:
    """What a child needs to reach the database and the artifact folders (picklable)."""

    database_url: str
    data_dir: str
    progress_interval_s: float
    torch_threads: int
    nice: int = 0
    """Added to the worker's niceness at start (0: same priority as the API)."""
    memory_mb: int | None = None
    """The worker's address-space limit (``RLIMIT_AS``; ``RLIMIT_DATA`` with the ``ray`` job
    backend), enforced by the OS; None: no limit."""
    job_disk_mb: float | None = None
    """How much disk a job's folder may take (MB); None: no bound (auction steps)."""
    min_free_disk_mb: int = 0
    """A job starts only while the data folder's disk has this much free (MB; 0: no check)."""
    job_backend: str = "local"
    """Where a job worker computes its units: ``local`` (itself) or ``ray``."""
    ray_address: str | None = None
    """The Ray cluster of the ``ray`` job backend."""
    ray_join_timeout_s: float = 30.0
    """How long a job's worker waits for the Ray head to answer before the job fails."""
    ray_max_retries: int = 0
    """Times the ``ray`` job backend runs a lost unit again."""
    review_margin: float = 0.0
    """``SRD_REVIEW_MARGIN``: an auction step holds the uploads it judges within it of a bar."""
    log_level: int = logging.INFO
    """The API's log level (``srd serve --log-level``): a worker logs as the API does."""


LOG_FORMAT = "%(levelname)s %(name)s: %(message)s"
"""The server's log lines, its workers' included."""


TaskFn = Callable[[WorkerContext, int], None]
ExitFn = Callable[[int, int | None, bool], None]
TimeoutFn = Callable[[int, float], None]
EndFn = Callable[[int, bool], None]


def error_summary(exc: BaseException) -> str:
    """The exception line plus the innermost frames, short enough for a status field. A frame
    names its file relative to the project or to ``site-packages`` (the field is public: it
    does not say where the server is installed)."""
    frames = traceback.extract_tb(exc.__traceback__)[-4:]
    for frame in frames:
        frame.filename = _shown_path(frame.filename)
    text = "".join(traceback.format_exception_only(type(exc), exc)).strip()
    if frames:
        shown = traceback.StackSummary.from_list(frames).format()
        text += "\nTraceback (innermost last):\n" + "".join(shown).rstrip()
    return text[-ERROR_LIMIT:]


_PROJECT = Path(__file__).resolve().parents[2]


def _shown_path(filename: str) -> str:
    """``filename`` relative to the project, or from ``site-packages/`` on, or its name."""
    path = Path(filename)
    if path.is_relative_to(_PROJECT):
        return path.relative_to(_PROJECT).as_posix()
    _, found, rest = filename.rpartition("/site-packages/")
    return found.strip("/") + "/" + rest if found else path.name


PRELOAD = (
    "server.work.fork_guard",
    "__main__",
    "torch",
    "screener",
    "server.auctions.steps",
    "server.jobs.worker",
)
"""What the fork server imports once, so that a forked child starts with it loaded (the API
process's main script too, which a child would otherwise import again); first, the guard that
ends the fork server with the API process."""

_fork_server_started = threading.Event()
_fork_server_lock = threading.Lock()


def process_context() -> SpawnContext | ForkServerContext:
    """How worker and screening processes start: forked from a fork server that imported
    torch, the screener and the task modules once (a child starts in milliseconds instead of
    the seconds of a fresh interpreter, and shares those pages), or spawned where there is no
    fork server. Either way a child begins from a clean import state, never from a copy of
    the API process (no inherited locks, sockets, threads or database connections)."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(list(PRELOAD))
    _start_fork_server()
    return context


def _start_fork_server() -> None:
    """Start the fork server (once per process) from a thread that lives as long as this
    process: its parent-death signal (``server.work.fork_guard``) is tied to that thread."""
    with _fork_server_lock:
        if _fork_server_started.is_set():
            return
        # The fork server is "python -c ...", whose first import path is the current folder,
        # and Python 3.11's fork server ignores the parent's path: without this its workers
        # could import another checkout's ``server`` (the folder's) than this process did.
        os.environ["PYTHONSAFEPATH"] = "1"

        def keep() -> None:
            from multiprocessing import forkserver

            try:
                forkserver.ensure_running()  # spawns it and returns; its imports go on there
            finally:
                _fork_server_started.set()
            threading.Event().wait()  # the fork server's parent thread: never ends

        threading.Thread(target=keep, name="fork-server", daemon=True).start()
        _fork_server_started.wait()


def usable_cpus() -> int:
    """The CPUs this process may use: those it may run on, fewer where a cgroup's quota
    (``docker run --cpus``, a Kubernetes limit: ``/sys/fs/cgroup/cpu.max``) allows less."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    with contextlib.suppress(OSError, ValueError):
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
        if quota != "max":
            return max(1, min(cpus or 1, math.ceil(int(quota) / int(period))))
    return max(1, cpus or 1)


def arm_parent_death_signal() -> None:
    """Ask Linux to SIGKILL this process when the thread that started it ends (elsewhere: no
    such signal, the callers' watchdogs act)."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def adopt_environment(environ: dict[str, str]) -> None:
    """Take the API process's environment as it was when this child was started (a fork
    server's children would otherwise inherit the fork server's, as it was at its start)."""
    if environ != os.environ:
        os.environ.clear()
        os.environ.update(environ)


def die_with_parent(parent_pid: int) -> None:
    """Make this child process end when the API process ``parent_pid`` does, and only when the
    API ends it (its own process group, SIGINT ignored; call it first thing), and give it its
    multiprocessing name in ``/proc`` (``srd-screening``, ``srd-auction-wor``...): a child's
    command line is the same for all, and benchmarks tell them apart by name.

    Linux delivers the parent-death signal (SIGKILL) when the *thread* that started the child
    ends. A forked child's parent is the fork server, which gets the same signal when the API
    process ends (``server.work.fork_guard``): a ``kill -9`` of the API ends both at once. A
    spawned child must be started from a thread that lives as long as it should (the pool
    supervisors, the screening keeper). The parent-pid watchdog covers other systems, where
    the fork server exits once the API is gone and no child holds its "alive" pipe open
    (this one lets go of its copy).
    """
    forked = os.getppid() != parent_pid
    if forked:
        _release_fork_server()
    # A child stops when the API stops it, not with its terminal: Ctrl-C, or a signal to the
    # server's process group (``timeout``, ``kill -- -PGID``), had ended every child at once,
    # failing the jobs they ran, while the API was still shutting down in order.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # the fork server ignores it (fork_guard)
    if hasattr(os, "setpgrp"):
        with contextlib.suppress(OSError):
            os.setpgrp()
    watched = os.getppid()
    arm_parent_death_signal()
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            name = multiprocessing.current_process().name.encode()[:15]
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_NAME, name)

    def watch() -> None:
        while True:
            if os.getppid() != watched:
                os._exit(70)
            time.sleep(PARENT_WATCH_S)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    if os.getppid() != watched or not _alive(parent_pid):  # it died before the signal was armed
        os._exit(70)


def _release_fork_server() -> None:
    """Close this forked child's copy of the fork server's "alive" pipe (multiprocessing hands
    one to every child so that it could fork more): the fork server then sees the pipe's end,
    and exits, as soon as the API process is gone. Our children fork nothing from it (a
    cheetah job draws its GIF in a plain subprocess that ends with it: ``sim.cheetah.render``)."""
    from multiprocessing import forkserver

    server = getattr(forkserver, "_forkserver", None)
    fd = getattr(server, "_forkserver_alive_fd", None)
    if server is not None and fd is not None:
        with contextlib.suppress(OSError):
            os.close(fd)
        server._forkserver_alive_fd = None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def freeze_heap() -> None:
    """Exempt what the process has imported and built so far from garbage collection.

    A process that imports torch, SQLAlchemy and pydantic holds a million or so container
    objects that live as long as it does; every full collection would walk them all (over
    100 ms here). In a worker that can happen inside a database transaction, holding SQLite's
    write lock the whole time, and in the API it stalls every request in flight. Call it once
    the imports are done; objects created afterwards are collected as usual.
    """
    gc.collect()
    gc.freeze()


def _worker_main(
    task: TaskFn,
    context: WorkerContext,
    conn: Connection,
    parent_pid: int,
    environ: dict[str, str],
) -> None:
    """A worker process: run each task id received, answer it when done, until the pipe ends."""
    die_with_parent(parent_pid)
    adopt_environment(environ)
    logging.basicConfig(level=context.log_level, format=LOG_FORMAT)
    if context.memory_mb is not None:
        limit = context.memory_mb << 20
        # A Ray driver maps the cluster's shared object store (gigabytes of address space):
        # there the limit is on the process's own data (heap and private mappings).
        kind = resource.RLIMIT_DATA if context.job_backend == "ray" else resource.RLIMIT_AS
        resource.setrlimit(kind, (limit, limit))
    if context.nice > 0 and hasattr(os, "nice"):
        with contextlib.suppress(OSError):
            os.nice(context.nice)  # background work yields to the API under load
    import torch

    torch.set_num_threads(context.torch_threads)  # leave the other cores to the API
    freeze_heap()
    while True:
        try:
            task_id = conn.recv()
        except EOFError:
            return
        # The time limit counts from here, not from the hand-out nor from when the supervisor
        # reads this: Linux's monotonic clock is one clock for every process.
        conn.send((STARTED, time.monotonic()))
        task(context, task_id)
        conn.send((DONE, time.monotonic()))


@dataclass
class _Worker:
    """One worker process, its end of the pipe, and the task it is running (if any)."""

    process: BaseProcess
    conn: Connection
    task_id: int | None = None
    tasks_done: int = 0
    cancelled_at: float | None = None  # when SIGTERM was sent for the current task
    started_at: float | None = None  # when the worker began the current task (None: not yet)
    timed_out: bool = False  # the current task was stopped at the time limit


class WorkerPool:
    """Runs ``task(context, task_id)`` in spawned worker processes, ``max_workers`` at a time.

    A worker process runs tasks one after another (``tasks_per_process`` of them, None: no
    limit), so the imports a task needs (torch...) are paid once, not per task; once the pool
    has had work, one idle worker is kept started ahead of need. A task is
    cancelled by terminating its process; a process that dies while running a task reports
    that task to ``on_exit`` with its exit code and whether it had begun the task (a worker
    killed between the hand-out and its word that it began ran none of it), unless cancelled
    or the pool is stopping.
    A task still running ``timeout_s`` after its worker began it (the worker says so over its
    pipe, once its interpreter is up: a fresh worker's imports are not the task's time) is
    stopped the same way and reported to ``on_timeout`` with the limit. Every task that is
    over, however it ended (done, died, stopped, or dropped from the queue by ``cancel``), is
    then reported to ``on_end``, with whether it was done (its worker said so).
    """

    def __init__(
        self,
        *,
        name: str,
        task: TaskFn,
        context: WorkerContext,
        max_workers: int,
        on_exit: ExitFn,
        tasks_per_process: int | None = None,
        timeout_s: float | None = None,
        on_timeout: TimeoutFn | None = None,
        on_end: EndFn | None = None,
    ) -> None:
        if (timeout_s is None) != (on_timeout is None):
            raise ValueError("a time limit needs its on_timeout report, and the other way round")
        self.name = name
        self._timeout_s = timeout_s
        self._on_timeout = on_timeout
        self._task = task
        self._context = context
        self._max_workers = max_workers
        self._tasks_per_process = tasks_per_process
        self._on_exit = on_exit
        self._on_end = on_end
        self._over: list[tuple[int, bool]] = []  # tasks over since last reported, and if done
        self._process_context = process_context()
        self._queue: deque[int] = deque()
        self._workers: list[_Worker] = []
        self._lock = threading.Lock()
        self._wake_reader, self._wake_writer = multiprocessing.Pipe(duplex=False)
        self._stopping = False
        self._used = False
        self._thread = threading.Thread(target=self._supervise, name=f"{name}-pool", daemon=True)

    def start(self) -> None:
        """Start the supervisor thread (it starts every worker process, see die_with_parent)."""
        self._thread.start()

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            self._wake_writer.send_bytes(b"")

    def submit(self, task_id: int) -> None:
        """Queue a task (ignored when it is already queued or running)."""
        with self._lock:
            running = any(w.task_id == task_id for w in self._workers)
            if not running and task_id not in self._queue:
                self._queue.append(task_id)
        self._wake()

    def cancel(self, task_id: int) -> None:
        """Drop a queued task or terminate the process running it (its end is not reported)."""
        with self._lock:
            if task_id in self._queue:
                self._queue.remove(task_id)
                self._over.append((task_id, False))
            for worker in self._workers:
                if worker.task_id == task_id and worker.cancelled_at is None:
                    worker.cancelled_at = time.monotonic()
                    worker.process.terminate()
        self._wake()

    def pid(self, task_id: int) -> int | None:
        """The process id running a task, if any."""
        with self._lock:
            for worker in self._workers:
                if worker.task_id == task_id:
                    return worker.process.pid
            return None

    def shutdown(self) -> None:
        """Stop the supervisor and the workers (unfinished tasks resume at the next start)."""
        with self._lock:
            self._stopping = True
            self._queue.clear()
        self._wake()
        if self._thread.is_alive():
            self._thread.join()
        for worker in self._workers:
            worker.process.terminate()
        for worker in self._workers:
            worker.process.join(TERMINATE_GRACE_S)
            if worker.process.is_alive():
                worker.process.kill()
                worker.process.join()
            worker.conn.close()
        self._workers.clear()

    def _supervise(self) -> None:
        refused = 0  # passes in a row whose _assign failed (logged ever more rarely)
        while True:
            with self._lock:
                if self._stopping:
                    return
                ended = self._collect()
                over, self._over = self._over, []
                try:
                    self._assign()
                except Exception:  # a worker that cannot start now: the next pass tries again
                    refused += 1
                    if refused & (refused - 1) == 0:  # the 1st, 2nd, 4th ... in a row
                        log.exception(
                            "%s: starting or handing work to a worker failed (%d times in a row)",
                            self.name,
                            refused,
                        )
                else:
                    refused = 0
                waitables: list[Any] = [self._wake_reader]
                waitables += [w.conn for w in self._workers if w.task_id is not None]
                waitables += [w.process.sentinel for w in self._workers]
            for task_id, code, timed_out, began in ended:
                try:
                    if timed_out:
                        assert self._on_timeout is not None and self._timeout_s is not None
                        self._on_timeout(task_id, self._timeout_s)
                    else:
                        self._on_exit(task_id, code, began)
                except Exception:
                    log.exception("%s: handling the end of task %d failed", self.name, task_id)
            self._report_over(over)
            for ready in wait(waitables, timeout=self._sleep_s()):
                if ready is self._wake_reader:
                    with contextlib.suppress(EOFError, OSError):
                        self._wake_reader.recv_bytes()

    def _report_over(self, over: list[tuple[int, bool]]) -> None:
        if self._on_end is None:
            return
        for task_id, done in over:
            try:
                self._on_end(task_id, done)
            except Exception:
                log.exception("%s: reporting the end of task %d failed", self.name, task_id)

    def _collect(self) -> list[tuple[int, int | None, bool, bool]]:
        """Free the workers whose task finished; stop the ones over the time limit; drop dead
        ones, returning what they ran (task, exit code, whether it was stopped at the limit,
        whether the worker had begun it)."""
        ended: list[tuple[int, int | None, bool, bool]] = []
        now = time.monotonic()
        for worker in list(self._workers):
            if worker.task_id is not None and worker.process.is_alive():
                if worker.cancelled_at is None:
                    self._read(worker)
                if self._over_limit(worker, now) and worker.cancelled_at is None:
                    worker.cancelled_at, worker.timed_out = now, True
                    worker.process.terminate()
                if worker.cancelled_at is not None:
                    if now - worker.cancelled_at > TERMINATE_GRACE_S:
                        worker.process.kill()
                    continue
                if worker.task_id is None and self._retired(worker):
                    worker.conn.close()  # the worker sees EOF and exits
            if not worker.process.is_alive():
                worker.process.join()
                if worker.cancelled_at is None:
                    self._read(worker)  # what it said before it died: begun, or even done
                worker.conn.close()
                self._workers.remove(worker)
                if worker.task_id is not None and (worker.cancelled_at is None or worker.timed_out):
                    began = worker.started_at is not None
                    ended.append((worker.task_id, worker.process.exitcode, worker.timed_out, began))
                if worker.task_id is not None:
                    self._over.append((worker.task_id, False))
        return ended

    def _read(self, worker: _Worker) -> None:
        """Take what the worker said about its task: begun (the clock starts) or done."""
        with contextlib.suppress(EOFError, OSError):
            while worker.task_id is not None and worker.conn.poll():
                said, at = worker.conn.recv()
                if said == STARTED:
                    worker.started_at = at
                else:
                    self._over.append((worker.task_id, True))
                    worker.task_id, worker.tasks_done = None, worker.tasks_done + 1

    def _sleep_s(self) -> float:
        """How long the supervisor may sleep: a tick, or less when a running task reaches its
        time limit sooner (a limit is kept to within scheduling delays, not to a tick)."""
        with self._lock:
            starts = [w.started_at for w in self._workers if w.task_id is not None]
        known = [s for s in starts if s is not None]
        if self._timeout_s is None or not known:
            return SUPERVISOR_TICK_S
        due = min(known) + self._timeout_s - time.monotonic()
        return min(SUPERVISOR_TICK_S, max(due, 0.0) + 0.001)

    def _over_limit(self, worker: _Worker, now: float) -> bool:
        """A task begun longer ago than the limit (a worker still starting up is not timed:
        its interpreter and imports are not the task's time)."""
        if worker.task_id is None or worker.started_at is None or self._timeout_s is None:
            return False
        return now - worker.started_at > self._timeout_s

    def _retired(self, worker: _Worker) -> bool:
        limit = self._tasks_per_process
        return limit is not None and worker.tasks_done >= limit

    def _assign(self) -> None:
        """Give queued tasks to idle workers (starting workers up to the limit); once the pool
        has had work, keep one spare worker started so the next task need not wait for a fresh
        interpreter (an idle server starts none)."""
        self._hand_out()
        idle = [w for w in self._workers if w.task_id is None and not self._retired(w)]
        if self._used and not idle and len(self._workers) < self._max_workers:
            self._start_worker()

    def _hand_out(self) -> None:
        while self._queue:
            idle = [w for w in self._workers if w.task_id is None and not self._retired(w)]
            if idle:
                worker = idle[0]
            elif len(self._workers) < self._max_workers:
                worker = self._start_worker()
            else:
                return
            task_id = self._queue.popleft()
            try:
                worker.conn.send(task_id)
            except OSError:  # it died since it was last looked at (killed): the task waits,
                self._queue.appendleft(task_id)  # first in line, for the next pass, which
                worker.process.kill()  # reaps this worker (its sentinel wakes that pass)
                return
            worker.task_id = task_id
            worker.cancelled_at, worker.timed_out, worker.started_at = None, False, None
            self._used = True

    def _start_worker(self) -> _Worker:
        ours, theirs = multiprocessing.Pipe(duplex=True)
        process = self._process_context.Process(
            target=_worker_main,
            args=(self._task, self._context, theirs, os.getpid(), dict(os.environ)),
            name=f"srd-{self.name}-worker",
        )
        try:
            process.start()
        except BaseException:  # the system refused it (EAGAIN, ENOMEM): no pipe left open
            ours.close()
            raise
        finally:
            theirs.close()
        worker = _Worker(process, ours)
        self._workers.append(worker)
        return worker
