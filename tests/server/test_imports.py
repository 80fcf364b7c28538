"""The API process loads no tensor code: the screening process and the workers do.

Importing torch takes seconds; an API process that does not starts answering that much
sooner, and spawns its screening process that much sooner too.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import httpx

from server.cli.launch import ServerProcess
from tests.support.factories import honest, saboteur, unique
from tests.support.server import ADMIN, ADMIN_TOKEN, wait_for

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


def test_srd_answers_help_and_bad_input_without_torch(tmp_path: Path) -> None:
    """Only a manifest to screen, or a run to make, loads torch: ``srd screen --help``, a
    malformed file and an experiment's bad option are answered at once (before, each took the
    2 s of importing torch)."""
    bad = tmp_path / "bad.json"
    bad.write_text('{"participant": "x"}')
    run = "from click.testing import CliRunner\nfrom server.cli import cli\n"
    helped = f"{run}assert CliRunner().invoke(cli, ['screen', '--help']).exit_code == 0"
    assert _loaded(helped) == []
    refused = f"{run}assert CliRunner().invoke(cli, ['screen', {str(bad)!r}]).exit_code == 2"
    assert _loaded(refused) == []
    for kind in ("fish", "lavaland", "cheetah", "agents"):
        bad_option = (
            f"{run}assert CliRunner().invoke(cli, [{kind!r}, '--seed', '-1']).exit_code == 2"
        )
        assert _loaded(bad_option) == [], kind
    helped = f"{run}assert CliRunner().invoke(cli, ['agents', '--help']).exit_code == 0"
    assert _loaded(helped) == []


def test_the_market_rules_and_the_verdict_type_load_without_torch() -> None:
    rules = "from sim.market import MarketConfig, design_changes, fish_on_sale"
    assert _loaded(f"{rules}\nfrom screener import Verdict") == []


def test_the_engine_still_loads_on_first_use() -> None:
    loaded = _loaded("from sim.market import Market\nfrom screener import screen_many\nscreen_many")
    assert "torch" in loaded and "sim.market.engine" in loaded


def test_a_running_server_keeps_torch_out_of_its_api_process(tmp_path: Path) -> None:
    """``srd serve`` started, a model accepted and one refused, an auction played to its end
    and its votes explained: the API process never mapped torch's library (its screening pool
    and workers judge and play). Its start used to import the market-impact test, torch and
    all, to hash the screener's secret: a second more of start, 300 MB more of memory."""
    with ServerProcess(
        database_url=f"sqlite:///{tmp_path / 'srd.db'}",
        data_dir=tmp_path,
        admin_token=ADMIN_TOKEN,
        extra_env={"SRD_REVIEW_MARGIN": "0"},  # the honest models accepted, none held
    ) as server, httpx.Client(base_url=server.url, timeout=60) as client:  # fmt: skip
        assert server.process is not None
        maps = Path(f"/proc/{server.process.pid}/maps")
        models = [client.post("/submit", json=honest(unique("light"), seed)) for seed in range(3)]
        assert [m.json()["status"] for m in models] == ["accepted"] * 3
        refused = client.post("/submit", json=saboteur(unique("light-sab")))
        assert refused.json()["status"] == "refused", refused.text
        created = client.post("/auctions", json={"n_fish": 1, "seed": 0}, headers=ADMIN)
        auction_id = created.json()["auction_id"]
        wait_for(
            lambda: client.get(f"/auctions/{auction_id}").json(),
            lambda state: state["status"] == "finished",
            timeout_s=60,
        )
        votes = client.get(f"/auctions/{auction_id}/iterations/0/votes")
        assert votes.status_code == 200, votes.text
        voter = votes.json()["votes"][0]["model_id"]
        for path in (f"votes/{voter}", f"votes/{voter}/weights"):
            explained = client.get(f"/auctions/{auction_id}/iterations/0/{path}")
            assert explained.status_code == 200, explained.text
        assert "libtorch" not in maps.read_text()
