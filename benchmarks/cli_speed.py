"""How fast the command line answers, timed as whole processes (start-up and imports included).

Measures, each the median of ``--runs`` runs: ``srd --help``, ``python -c "import torch"``
(the floor of any command that screens or simulates) and ``srd screen examples/honest.json``.
Targets: ``srd --help`` within 0.5 s; ``srd screen FILE`` within torch's own import time plus
0.5 s. Prints the figures and whether each target is met.

The command line loads a command's modules with the cyclic garbage collector paused (see
``server.cli``), which makes torch's own import faster inside ``srd`` than in a bare
``python -c "import torch"``. So the benchmark also times torch imported the same way and
prints the margin over that too: the cost of everything ``srd screen`` does besides loading
torch.

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


def timed(commands: dict[str, list[str]], runs: int) -> dict[str, float]:
    """The median wall time of each command over ``runs`` rounds, after one untimed warm-up
    round; each round runs every command once, in turn, so a drift in the machine's speed
    falls on all of them alike."""
    times: dict[str, list[float]] = {name: [] for name in commands}
    for round_index in range(runs + 1):
        for name, command in commands.items():
            start = time.perf_counter()
            subprocess.run(command, cwd=ROOT, capture_output=True, check=False)
            if round_index:
                times[name].append(time.perf_counter() - start)
    return {name: statistics.median(values) for name, values in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=7)
    args = parser.parse_args()
    medians = timed(
        {
            "help": [SRD, "--help"],
            "torch": [sys.executable, "-c", "import torch"],
            "paused": [
                sys.executable,
                "-c",
                "import gc; gc.disable(); import torch; gc.collect()",
            ],
            "screen": [SRD, "screen", "examples/honest.json"],
        },
        args.runs,
    )
    help_s, torch_s, paused_s, screen_s = (
        medians[name] for name in ("help", "torch", "paused", "screen")
    )
    print(
        f"srd --help                      {help_s:6.3f} s  (target ≤ {HELP_TARGET_S} s: "
        f"{'met' if help_s <= HELP_TARGET_S else 'missed'})"
    )
    print(f"python -c 'import torch'        {torch_s:6.3f} s")
    print(f"  the same, collector paused    {paused_s:6.3f} s")
    over = screen_s - torch_s
    print(
        f"srd screen examples/honest.json {screen_s:6.3f} s  = torch import + {over:.3f} s "
        f"(target ≤ + {SCREEN_MARGIN_S} s: {'met' if over <= SCREEN_MARGIN_S else 'missed'})"
    )
    print(f"{'':32}          = paused torch import + {screen_s - paused_s:.3f} s")


if __name__ == "__main__":
    main()
