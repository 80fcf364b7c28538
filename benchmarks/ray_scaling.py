"""Job units on Ray against the local backend: the paper's full auction grid and a lavaland
job of 8 repeats, on this machine, local and on a Ray cluster of 1 and 2 CPUs.

Each experiment runs three ways through the same units (``sim.units``): in this process, one
unit after another (what the local job backend does), then with the Ray backend's runner
(``server.jobs.ray_backend.RayRunner``, what a job worker does with ``SRD_JOB_BACKEND=ray``) on
a fresh local Ray cluster of 1 CPU and of 2 CPUs. The results must be equal (wall times
aside). Measured as well: starting a cluster, joining it as a driver, one empty task's round
trip, the per-task cost of many empty tasks, and a fresh worker's first unit (its imports).

From the per-unit costs measured locally it projects the time on N machines of C cores:
T ≈ join + a fresh worker's imports + makespan of the measured units on N·C cores (longest
first, each plus the per-task cost) + assembly, printing the arithmetic. One torch thread
everywhere; the machine is shared: the numbers are noisy, the ratios more telling.

Run: ``.venv/bin/python benchmarks/ray_scaling.py [--repeats 8] [--trials 10]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # for tests.support

from server.jobs.ray_backend import RayRunner
from sim import units
from sim.experiment import Stopwatch, no_progress
from sim.units import Payload, Unit, UnitProgress
from studies.registry import KINDS, build_config
from tests.support.ray_head import RayHead

torch.set_num_threads(1)
EMPTY_TASKS = 200
"""Empty tasks timed for the per-task cost."""
MACHINES = (1, 2, 4, 8, 16, 32)
"""Cluster sizes projected."""
TIMES = ("elapsed_s", "simulation_s")


def without_times(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: without_times(v) for k, v in value.items() if k not in TIMES}
    if isinstance(value, list):
        return [without_times(v) for v in value]
    return value


def timed_local(kind: str, config: Any, unit_times: list[float]) -> units.UnitRunner:
    """The in-process runner, timing every unit."""
    decomposition = KINDS[kind].decomposition()

    def runner(plan: Sequence[Unit], progress: UnitProgress) -> Iterator[tuple[int, Payload]]:
        for index, unit in enumerate(plan):
            start = time.perf_counter()
            payload = decomposition.compute(config, unit, no_progress)
            unit_times.append(time.perf_counter() - start)
            yield index, payload

    return runner


def run(kind: str, config: Any, runner: units.UnitRunner) -> tuple[dict[str, Any], float]:
    decomposition = KINDS[kind].decomposition()
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        result = units.run(decomposition, config, out_dir=Path(out), runner=runner)
        return result, time.perf_counter() - start


def assemble_time(kind: str, config: Any) -> float:
    """Time of the assembly alone (artifacts, figures), from payloads computed beforehand."""
    decomposition = KINDS[kind].decomposition()
    plan = decomposition.plan(config)
    payloads = [decomposition.compute(config, unit, no_progress) for unit in plan]
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        decomposition.assemble(
            config,
            plan,
            payloads,
            out_dir=Path(out),
            progress=no_progress,
            watch=Stopwatch(),
        )
        return time.perf_counter() - start


def join_time(head: RayHead) -> float:
    """Joining the cluster as a new driver process (what each Ray job worker pays), import of
    ray included."""
    code = (
        "import time; t = time.perf_counter(); import ray; "
        f"ray.init(address={head.address!r}, log_to_driver=False); "
        "print(time.perf_counter() - t)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        env={**os.environ, **head.env},
        capture_output=True,
        text=True,
        check=True,
    )
    return float(done.stdout.strip().splitlines()[-1])


def _empty() -> None:
    return None


def _imports() -> float:
    start = time.perf_counter()
    import sim.lavaland.experiment  # noqa: F401
    import studies.auctions  # noqa: F401

    return time.perf_counter() - start


def task_costs(ray: Any) -> dict[str, float]:
    """One empty task's round trip (on a fresh worker, then a warm one), the mean cost of many
    empty tasks, and a fresh worker's imports of the experiments."""
    empty = ray.remote(num_cpus=1)(_empty)
    start = time.perf_counter()
    ray.get(empty.remote())
    first = time.perf_counter() - start
    start = time.perf_counter()
    ray.get(empty.remote())
    warm = time.perf_counter() - start
    start = time.perf_counter()
    ray.get([empty.remote() for _ in range(EMPTY_TASKS)])
    per_task = (time.perf_counter() - start) / EMPTY_TASKS
    imports = ray.get(ray.remote(num_cpus=1)(_imports).remote())
    return {"first": first, "warm": warm, "per_task": per_task, "imports": imports}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=8)
    parser.add_argument("--trials", type=int, default=10)
    args = parser.parse_args()
    jobs = {
        "auction-study": build_config("auction-study", {"grid": True, "trials": args.trials}),
        "lavaland": build_config("lavaland", {"repeats": args.repeats}),
    }
    local = run_locally(jobs)
    overhead, ray_walls = run_on_ray(jobs, local)
    print()
    project(jobs, local, overhead, ray_walls)


def run_locally(jobs: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Each job in process on one core: its result, wall time, unit times and assembly time."""
    local: dict[str, dict[str, Any]] = {}
    for kind, config in jobs.items():
        unit_times: list[float] = []
        result, wall = run(kind, config, timed_local(kind, config, unit_times))
        local[kind] = {
            "result": result,
            "wall": wall,
            "units": unit_times,
            "assemble": assemble_time(kind, config),
        }
        print(
            f"{kind}: local (in process, one core): {wall:.1f} s, {len(unit_times)} units, "
            f"mean {statistics.mean(unit_times):.2f} s, max {max(unit_times):.2f} s, "
            f"assembly {local[kind]['assemble']:.2f} s"
        )
    return local


def run_on_ray(
    jobs: dict[str, Any], local: dict[str, dict[str, Any]]
) -> tuple[dict[str, float], dict[tuple[str, int], float]]:
    """Each job on a local Ray cluster of 1 then 2 CPUs, checked identical to the local result:
    the overheads measured on the 1-CPU cluster and the wall time per (job, CPUs)."""
    token = os.urandom(32).hex()  # one token for both clusters (Ray reads it once per process)
    overhead: dict[str, float] = {}
    ray_walls: dict[tuple[str, int], float] = {}
    for cpus in (1, 2):
        start = time.perf_counter()
        head = RayHead(cpus, token=token).start()
        cluster_start = time.perf_counter() - start
        os.environ.update(head.env)
        try:
            joined = join_time(head)
            import ray

            ray.init(address=head.address, log_to_driver=False)
            costs = task_costs(ray)
            ray.shutdown()  # the runners join again, as a job worker does
            print(
                f"Ray, {cpus} CPU: cluster start {cluster_start:.1f} s, a driver joins in "
                f"{joined:.2f} s (import of ray included), empty task {costs['first']:.3f} s "
                f"on a fresh worker, {costs['warm'] * 1000:.1f} ms warm, "
                f"{costs['per_task'] * 1000:.2f} ms each over {EMPTY_TASKS}; a fresh worker's "
                f"imports of the experiments {costs['imports']:.2f} s"
            )
            if cpus == 1:
                overhead = {"join": joined, **costs}
            for kind, config in jobs.items():
                runner = RayRunner(kind, config, address=head.address, max_retries=3, threads=1)
                result, wall = run(kind, config, runner)
                ray.shutdown()
                same = without_times(result) == without_times(local[kind]["result"])
                assert same, f"{kind}: Ray and local results differ"
                ray_walls[(kind, cpus)] = wall
                ratio = local[kind]["wall"] / wall
                print(f"  {kind}: {wall:.1f} s on Ray ({ratio:.2f}x local), results identical")
        finally:
            head.stop()
    return overhead, ray_walls


def project(
    jobs: dict[str, Any],
    local: dict[str, dict[str, Any]],
    overhead: dict[str, float],
    ray_walls: dict[tuple[str, int], float],
) -> None:
    """The projected wall time on N machines of C cores from the measured parts, and the
    projection checked against the measured walls on this machine."""
    cores = os.cpu_count() or 1
    for kind in jobs:
        unit_times = local[kind]["units"]
        n = len(unit_times)
        fixed = overhead["join"] + overhead["imports"]
        assembly = local[kind]["assemble"]
        print(
            f"{kind}: T(N machines of C cores) = join {overhead['join']:.2f} + imports "
            f"{overhead['imports']:.2f} + makespan of the {n} measured units on N·C cores "
            f"(longest first, each + {overhead['per_task'] * 1000:.1f} ms per task) + assembly "
            f"{assembly:.2f} s; sum of units {sum(unit_times):.2f} s"
        )
        for machines in MACHINES:
            span = makespan(unit_times, machines * cores, overhead["per_task"])
            print(
                f"  N = {machines:2d}, C = {cores}: {fixed:.2f} + {span:.2f} + {assembly:.2f} = "
                f"{fixed + span + assembly:.1f} s (local: {local[kind]['wall']:.1f} s)"
            )
        print(
            f"  at most {n} units run at once: beyond {n} cores the makespan is the longest "
            f"unit, {max(unit_times):.2f} s"
        )
        for cpus in (1, 2):
            span = makespan(unit_times, cpus, overhead["per_task"])
            print(
                f"  check on this machine, {cpus} CPU: projected {fixed + span + assembly:.1f} "
                f"s, measured {ray_walls[(kind, cpus)]:.1f} s"
            )


def makespan(unit_times: Sequence[float], slots: int, per_task: float) -> float:
    """When the last unit ends with ``slots`` cores, units handed out longest first to the
    core free soonest (what Ray's queue does with tasks of known length, at best)."""
    ends = [0.0] * min(slots, len(unit_times))
    for cost in sorted(unit_times, reverse=True):
        soonest = ends.index(min(ends))
        ends[soonest] += cost + per_task
    return max(ends)


if __name__ == "__main__":
    main()
