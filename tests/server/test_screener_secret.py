"""A deployment's screener secret (``SRD_SCREENER_SECRET``): the market-impact test meets
reference populations drawn from it, so a model tuned offline against the public screener's
populations is judged on others; ``srd screen`` reproduces a deployment's verdicts given it,
``srd serve`` hands it (from a secret file too) to the processes that screen, every verdict's
evidence and ``/healthz`` name the populations, and a server started on other populations than
the newest verdict's says so."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Any

import httpx
import pytest

from agents.manifest import parse_manifest
from screener import screen
from server.cli.launch import ServerProcess, srd_command
from tests.support.processes import serve_once
from tests.support.server import ADMIN_TOKEN

ROOT = Path(__file__).resolve().parents[2]
HOLDER = ROOT / "examples" / "red_team" / "opening-window-holder-a.json"
SECRET = "9f2c4e71b08d3a56c1e7f09b2d4a6c83e5f71b09d2c4a6e8f0b13d57a9c2e4f6"
OTHER = "0d8e6b4a2c9f7e5d3b1a0c8e6f4d2b9a7c5e3f1d0b8a6c4e2f9d7b5a3c1e0f8d"


def impact(evidence: list[dict[str, Any]]) -> dict[str, Any]:
    """The market-impact test's evidence."""
    (found,) = [e for e in evidence if e["test"] == "market-impact"]
    return found


def screened_with(secret: str) -> dict[str, Any]:
    """``srd screen --json`` of the holder in a process given ``secret`` as a variable."""
    done = subprocess.run(
        [*srd_command(), "screen", str(HOLDER), "--json"],
        env={**os.environ, "SRD_SCREENER_SECRET": secret},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode in (0, 1), done.stderr
    return dict(json.loads(done.stdout))


def keyed_server(folder: Path, secret: str) -> ServerProcess:
    """A server on ``folder``'s database whose secret comes from a secret file, as compose
    mounts it (with the newline an editor leaves)."""
    secrets = folder / f"secrets-{secret[:4]}"
    secrets.mkdir(exist_ok=True)
    (secrets / "srd_screener_secret").write_text(secret + "\n")
    return ServerProcess(
        database_url=f"sqlite:///{folder / 'srd.db'}",
        data_dir=folder / "data",
        admin_token=ADMIN_TOKEN,
        extra_env={"SRD_SECRETS_DIR": str(secrets), "SRD_SCREENER_SECRET": ""},
    )


def test_a_server_screens_on_its_secrets_populations_and_names_them(tmp_path: Path) -> None:
    holder = json.loads(HOLDER.read_text())
    public = impact(screen(parse_manifest(holder)).to_dict()["evidence"])
    keyed = screened_with(SECRET)
    mine = impact(keyed["evidence"])
    assert public["detail"]["populations"] == "public"
    assert mine["detail"]["populations"] not in ("public", SECRET)  # a marker, not the secret
    assert (mine["measured"], mine["bar"]) != (public["measured"], public["bar"])
    with keyed_server(tmp_path, SECRET) as server, httpx.Client(base_url=server.url) as client:
        health = client.get("/healthz").json()
        assert health["screener_populations"] == mine["detail"]["populations"]
        answer = client.post("/submit", json=holder, timeout=120)
        assert answer.status_code in (201, 422), answer.text
        stored = client.get(f"/models/{answer.json()['model_id']}").json()
    # judged on the secret's populations to the last digit, as srd screen does
    assert impact(stored["evidence"]) == mine and stored["status"] == keyed["status"]
    assert "SRD_SCREENER_SECRET's" in server.log_path.read_text()
    assert "other populations" not in server.log_path.read_text()
    # Restarted with another secret: it says the newest verdict was made on other populations.
    with keyed_server(tmp_path, OTHER) as server, httpx.Client(base_url=server.url) as client:
        assert (
            client.get("/healthz").json()["screener_populations"] != health["screener_populations"]
        )
    log = server.log_path.read_text()
    assert "the newest verdict stored was made on other populations" in log
    assert SECRET not in log and OTHER not in log


@pytest.mark.slow  # 22 s (three screenings on secret populations); the server's test stays
def test_srd_screen_takes_a_secret_the_environment_could_not_decode() -> None:
    """Bytes that are not UTF-8 in the variable are hashed as they are (the screener had
    failed on every manifest with them); white space around a secret does not count."""
    undecodable = screened_with("caf\udce9-" + SECRET)  # the byte 0xe9, as os.environ keeps it
    spaced = screened_with(f"  {SECRET}\n")
    plain = screened_with(SECRET)
    assert impact(spaced["evidence"]) == impact(plain["evidence"])
    populations = {impact(r["evidence"])["detail"]["populations"] for r in (undecodable, plain)}
    assert len(populations) == 2 and "public" not in populations


def test_a_secret_file_that_is_not_text_stops_the_start_in_one_line(tmp_path: Path) -> None:
    secrets = tmp_path / "secrets"
    secrets.mkdir()
    (secrets / "srd_screener_secret").write_bytes(b"caf\xe9-" + SECRET.encode())
    env = {
        **os.environ,
        "SRD_DATA_DIR": str(tmp_path / "data"),
        "SRD_DATABASE_URL": f"sqlite:///{tmp_path / 'srd.db'}",
        "SRD_SECRETS_DIR": str(secrets),
    }
    done = serve_once(env)
    assert done.returncode == 2, done.stderr
    (line,) = done.stderr.splitlines()
    assert line.startswith("srd serve: SRD_SECRETS_DIR=") and "screener_secret" in line
    assert "Traceback" not in done.stderr and SECRET not in done.stderr
