"""A deployment's screener secret (``SRD_SCREENER_SECRET``): the market-impact test meets
reference populations drawn from it, so a model tuned offline against the public screener's
populations is judged on others; ``srd screen`` reproduces a deployment's verdicts given it,
and ``srd serve`` hands it (from a secret file too) to the processes that screen."""

from __future__ import annotations

import json
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from agents.manifest import parse_manifest
from screener import screen
from server.cli.launch import ServerProcess, srd_command
from tests.support.server import ADMIN_TOKEN

ROOT = Path(__file__).resolve().parents[2]
HOLDER = ROOT / "examples" / "red_team" / "opening-window-holder-a.json"
SECRET = "a-deployment-secret-0123456789"


def impact(evidence: list[dict[str, Any]]) -> tuple[float, float]:
    """The market-impact test's (measured, bar)."""
    (found,) = [e for e in evidence if e["test"] == "market-impact"]
    return found["measured"], found["bar"]


def screened_with(secret: str) -> dict[str, Any]:
    """``srd screen --json`` of the holder in a process given ``secret``."""
    done = subprocess.run(
        [*srd_command(), "screen", str(HOLDER), "--json"],
        env={**os.environ, "SRD_SCREENER_SECRET": secret},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode in (0, 1), done.stderr
    return dict(json.loads(done.stdout))


@pytest.fixture(scope="module")
def keyed_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    """A server whose secret comes from a secret file, as compose mounts it."""
    data_dir = tmp_path_factory.mktemp("keyed")
    secrets = tmp_path_factory.mktemp("secrets")
    (secrets / "srd_screener_secret").write_text(SECRET + "\n")
    with ServerProcess(
        database_url=f"sqlite:///{data_dir / 'srd.db'}",
        data_dir=data_dir,
        admin_token=ADMIN_TOKEN,
        extra_env={"SRD_SECRETS_DIR": str(secrets), "SRD_SCREENER_SECRET": ""},
    ) as running:
        yield running


def test_a_secret_changes_the_populations_and_a_server_screens_with_its_own(
    keyed_server: ServerProcess,
) -> None:
    public = screen(parse_manifest(json.loads(HOLDER.read_text()))).to_dict()
    keyed = screened_with(SECRET)
    assert impact(keyed["evidence"]) != impact(public["evidence"])  # other populations
    with httpx.Client(base_url=keyed_server.url, timeout=120) as client:
        answer = client.post("/submit", json=json.loads(HOLDER.read_text()))
        assert answer.status_code in (201, 422), answer.text
        stored = client.get(f"/models/{answer.json()['model_id']}").json()
    # the server judged on the secret's populations, to the last digit, as srd screen does
    assert impact(stored["evidence"]) == impact(keyed["evidence"])
    assert stored["status"] == keyed["status"]
