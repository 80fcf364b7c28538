"""The screener's cost in the units of another commit: the same measurements, run by whichever
checkout is first on ``PYTHONPATH``, so two commits can be alternated in one hour on one
machine (the machine's speed changes from one session to the next, so only such pairs compare).

Prints, ms per manifest (CPU, one torch thread, best of 7 calls after two): ``screen_many`` of a
factory batch of 64 (seed 0), of their fine-tuned versions at the door, ``rescreen`` of those
fine-tuned versions, ``screen`` of 16 factory manifests one by one, and ``screen`` of each
model in ``--holders`` (a JSON list of manifests: fastest, median, 90th percentile, slowest).
``--save-holders FILE [--count N]`` writes N holders (default 8) as the checkout it runs in
defines them (factory models that hold somewhere on the decisive row and pass the rules), so
both commits judge the same ones.

    .venv/bin/python benchmarks/screener_ab.py --save-holders /tmp/holders.json --count 300
    for commit in OLD NEW; do
        PYTHONPATH=<checkout of commit> .venv/bin/python benchmarks/screener_ab.py \\
            --holders /tmp/holders.json
    done
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
# The measured checkout is the one first on PYTHONPATH, else this one; never this folder
# (its screener.py would hide the screener package).
sys.path[:] = [entry for entry in sys.path if Path(entry or ".").resolve() != HERE]
sys.path.append(str(HERE.parent))

from agents.batch import from_manifests  # noqa: E402
from agents.manifest import Manifest  # noqa: E402
from agents.negotiator import honest_manifest  # noqa: E402
from screener import rescreen, screen, screen_many  # noqa: E402
from tests.support.corpus import fine_tuned  # noqa: E402


def _best(call: Callable[[], object], calls: int = 7) -> float:
    """CPU ms of the fastest of ``calls`` calls after two unmeasured ones."""
    call()
    call()
    times = []
    for _ in range(calls):
        start = time.process_time()
        call()
        times.append(time.process_time() - start)
    return min(times) * 1e3


def _save_holders(path: Path, count: int) -> None:
    from screener.checks import cheap_checks, failed_any

    rng = np.random.default_rng(1)
    holders: list[Manifest] = []
    while len(holders) < count:
        models = [honest_manifest(rng, f"holder-{len(holders)}-{i}") for i in range(256)]
        cheap = cheap_checks(from_manifests(models))
        keep = cheap.holds & ~failed_any(cheap.groups)
        holders += [m for m, k in zip(models, keep, strict=True) if k]
    path.write_text(json.dumps([m.model_dump_json() for m in holders[:count]]))
    print(f"{path}: {count} holders")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--holders", type=Path, help="JSON list of manifests to screen alone")
    parser.add_argument("--save-holders", type=Path, metavar="FILE")
    parser.add_argument("--count", type=int, default=8, help="holders to save")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.save_holders:
        _save_holders(args.save_holders, args.count)
        return
    rng = np.random.default_rng(0)
    made = [honest_manifest(rng, f"h{i}") for i in range(64)]
    tuned = fine_tuned(made, rng)
    tuned_batch = from_manifests(tuned)
    figures = {
        "factory batch of 64": _best(lambda: screen_many(made)) / 64,
        "fine-tuned at the door, 64": _best(lambda: screen_many(tuned)) / 64,
        "re-screened, 64": _best(lambda: rescreen(tuned_batch)) / 64,
        "one manifest alone (16 in turn)": _best(lambda: [screen(m) for m in made[:16]], 3) / 16,
    }
    if args.holders:
        holders = [Manifest.model_validate_json(t) for t in json.loads(args.holders.read_text())]
        alone = [_best(lambda m=m: screen(m), 3) for m in holders]
        figures[f"one holder alone, fastest of {len(alone)}"] = min(alone)
        figures["one holder alone, median"] = float(np.median(alone))
        figures["one holder alone, 90th percentile"] = float(np.percentile(alone, 90))
        figures["one holder alone, slowest"] = max(alone)
    for name, ms in figures.items():
        print(f"{name:>34}: {ms:.2f} ms")


if __name__ == "__main__":
    main()
