"""A throw-away Ray cluster on this machine for tests and benchmarks.

``python -m tests.support.ray_head CPUS`` starts a one-node Ray instance (token authentication
on, dashboard off, its own temporary folder), prints the port of its GCS, and stops it when
its stdin closes. ``RayHead`` runs that as a child process in a session of its own and stops
exactly that cluster: nothing else on the machine is touched.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from types import TracebackType

START_TIMEOUT_S = 120.0
STOP_TIMEOUT_S = 30.0


def main() -> None:
    import ray

    temp = Path(sys.argv[2])
    context = ray.init(
        num_cpus=int(sys.argv[1]),
        include_dashboard=False,
        _node_ip_address="127.0.0.1",
        _temp_dir=str(temp),
    )
    port = context.address_info["gcs_address"].rsplit(":", 1)[1]
    print(port, flush=True)
    sys.stdin.read()
    ray.shutdown()


class RayHead:
    """A local Ray cluster of ``cpus`` CPUs in a child process; ``address`` and ``env`` (the
    variables a driver needs: the address and the cluster's token) once started."""

    def __init__(self, cpus: int, token: str | None = None) -> None:
        self.cpus = cpus
        self.token = token or secrets.token_hex(32)
        self.env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": self.token}
        # Short: Ray's unix sockets live under it (their paths are limited to 107 bytes).
        self.temp = Path(tempfile.mkdtemp(prefix="srdray"))
        self.address = ""
        self.process: subprocess.Popen[str] | None = None

    def start(self) -> RayHead:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "tests.support.ray_head", str(self.cpus), str(self.temp)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=(self.temp / "head.log").open("w"),
            text=True,
            env={**os.environ, **self.env},
            cwd=Path(__file__).resolve().parents[2],
            start_new_session=True,  # the test's Ctrl-C stops the test, not the cluster
        )
        assert self.process.stdout is not None
        line = self.process.stdout.readline().strip()
        if not line.isdigit():
            self.stop()
            raise RuntimeError(f"the Ray head did not start; see {self.temp / 'head.log'}")
        self.address = f"127.0.0.1:{line}"
        return self

    def worker_pids(self, title: str) -> list[int]:
        """Processes of this cluster whose title starts with ``ray::<title>`` (Ray titles a
        worker after the task it runs)."""
        return [
            pid
            for pid, (_, command) in self._descendants().items()
            if command.startswith(f"ray::{title}")
        ]

    def _descendants(self) -> dict[int, tuple[str, str]]:
        """Every process below the head: pid → (start time, command line)."""
        assert self.process is not None
        parents: dict[int, int] = {}
        seen: dict[int, tuple[str, str]] = {}
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                command = (entry / "cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue
            parents[int(entry.name)] = int(stat[1])
            seen[int(entry.name)] = (stat[19], command)
        found = {}
        for pid in seen:
            up = parents.get(pid, 0)
            while up > 1 and up != self.process.pid:
                up = parents.get(up, 0)
            if up == self.process.pid:
                found[pid] = seen[pid]
        return found

    def stop(self) -> None:
        if self.process is None:
            return
        started = self._descendants() if self.process.poll() is None else {}
        if self.process.poll() is None:
            assert self.process.stdin is not None
            self.process.stdin.close()  # the head shuts Ray down and exits
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(STOP_TIMEOUT_S)
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.process.pid, signal.SIGKILL)
        self.process.wait()
        for pid, (start, _) in started.items():  # any of its processes that outlived it
            with contextlib.suppress(OSError, IndexError):
                stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
                if stat[19] == start:
                    os.kill(pid, signal.SIGKILL)
        shutil.rmtree(self.temp, ignore_errors=True)

    def __enter__(self) -> RayHead:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()


if __name__ == "__main__":
    main()
