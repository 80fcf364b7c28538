"""The API process loads no tensor code: the screening process and the workers do.

Importing torch takes seconds; an API process that does not starts answering that much
sooner, and spawns its screening process that much sooner too.
"""

from __future__ import annotations

import subprocess
import sys

HEAVY = ("sim.market.engine", "agents.batch", "screener.impact", "numba", "mujoco", "gymnasium")
"""Modules that bring the tensors (or a simulator) with them."""

PROBE = """
import sys
heavy = {heavy!r}
print(",".join(sorted(m for m in sys.modules if m.split(".")[0] == "torch" or m in heavy)))
"""


def _loaded(code: str) -> list[str]:
    """The torch and tensor modules loaded once ``code`` has run in a fresh interpreter."""
    probe = code + "\n" + PROBE.format(heavy=HEAVY)
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return [name for name in done.stdout.strip().split(",") if name]


def test_the_api_app_and_its_routes_load_without_torch() -> None:
    assert _loaded("from server.app import create_app\ncreate_app()") == []


def test_the_openapi_document_and_every_job_check_load_no_simulation() -> None:
    """Describing the jobs' options (the first ``GET /openapi.json``) and checking a job's
    options and cost (``POST /jobs``) read the configs only: before, they imported torch, numba,
    PIL and Gymnasium into the API process on its event loop (+275 MB, seconds of stall)."""
    code = (
        "from server.app import create_app\n"
        "create_app().openapi()\n"
        "from studies.registry import KINDS, build_config\n"
        "for kind in KINDS:\n"
        "    build_config(kind, {}).cost()\n"
    )
    assert _loaded(code) == []


def test_the_market_rules_and_the_verdict_type_load_without_torch() -> None:
    rules = "from sim.market import MarketConfig, design_changes, fish_on_sale"
    assert _loaded(f"{rules}\nfrom screener import Verdict") == []


def test_the_engine_still_loads_on_first_use() -> None:
    loaded = _loaded("from sim.market import Market\nfrom screener import screen_many\nscreen_many")
    assert "torch" in loaded and "sim.market.engine" in loaded
