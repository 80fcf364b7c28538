"""How fast the command line answers, timed as whole processes (start-up and imports included).

Measures, each the median of ``--runs`` runs: ``srd --help``, ``python -c "import torch"``
(the floor of any command that screens or simulates) and ``srd screen examples/honest.json``.
Targets: ``srd --help`` within 0.5 s; ``srd screen FILE`` within torch's own import time plus
0.5 s. Prints the figures and whether each target is met.

Run: ``.venv/bin/python benchmarks/cli_speed.py [--runs 7]``
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRD = str(Path(sys.executable).with_name("srd"))
HELP_TARGET_S = 0.5
SCREEN_MARGIN_S = 0.5


def timed(command: list[str], runs: int) -> float:
    """The median wall time of ``command`` over ``runs`` runs (after one untimed warm-up)."""
    subprocess.run(command, cwd=ROOT, capture_output=True, check=False)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(command, cwd=ROOT, capture_output=True, check=False)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=7)
    args = parser.parse_args()
    help_s = timed([SRD, "--help"], args.runs)
    torch_s = timed([sys.executable, "-c", "import torch"], args.runs)
    screen_s = timed([SRD, "screen", "examples/honest.json"], args.runs)
    print(
        f"srd --help                      {help_s:6.3f} s  (target ≤ {HELP_TARGET_S} s: "
        f"{'met' if help_s <= HELP_TARGET_S else 'missed'})"
    )
    print(f"python -c 'import torch'        {torch_s:6.3f} s")
    over = screen_s - torch_s
    print(
        f"srd screen examples/honest.json {screen_s:6.3f} s  = torch import + {over:.3f} s "
        f"(target ≤ + {SCREEN_MARGIN_S} s: {'met' if over <= SCREEN_MARGIN_S else 'missed'})"
    )


if __name__ == "__main__":
    main()
