"""The README's quick start runs as pasted: its shell block against a live ``srd serve`` on a
fresh database, then what it must have done, checked through the API."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from server.cli.launch import ServerProcess
from server.config import Settings

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
BLOCK_TIMEOUT_S = 180


def quick_start_block() -> str:
    """The shell block of the README's "Quick start" section that talks to the server."""
    text = README.read_text()
    section = text.split("\n## Quick start\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```sh\n(.*?)```", section, flags=re.DOTALL)
    talking = [block for block in blocks if "SRD_URL" in block]
    assert len(talking) == 1, "the quick start has one block that talks to the server"
    return talking[0]


def run_block(block: str, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """A documented shell block, run as pasted (stopping at its first failing command)."""
    run = subprocess.run(
        ["bash", "-e", "-u", "-o", "pipefail", "-c", block],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=BLOCK_TIMEOUT_S,
    )
    assert run.returncode == 0, f"stdout:\n{run.stdout}\nstderr:\n{run.stderr}"
    return run


def test_the_block_defaults_to_what_srd_serve_does_by_default() -> None:
    block = quick_start_block()
    fields = Settings.model_fields
    default_url = f"http://{fields['host'].default}:{fields['port'].default}"
    assert f"${{SRD_URL:-{default_url}}}" in block
    assert f"${{SRD_DATA_DIR:-{fields['data_dir'].default}}}" in block
    assert fields["database_url"].default == "sqlite:///./srd.db"  # what the prose says
    assert ".venv/bin/srd serve" in README.read_text().split("\n## Quick start\n", 1)[1]


def test_the_population_files_are_what_their_script_writes() -> None:
    folder = ROOT / "examples" / "population"
    sys.path.insert(0, str(folder))
    try:
        import make_population
    finally:
        sys.path.remove(str(folder))
    written = make_population.population()
    assert sorted(written) == sorted(p.name for p in folder.glob("*.json"))
    for name, manifest in written.items():
        assert (folder / name).read_text() == make_population.text(manifest)
    descriptions = {m["description"] for m in written.values()}
    assert len(descriptions) == len(written)  # all different


def test_the_quick_start_runs_as_pasted(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    server = ServerProcess(database_url=f"sqlite:///{tmp_path / 'srd.db'}", data_dir=data_dir)
    with server:  # no SRD_ADMIN_TOKEN: the server writes one, as on a first start
        env = {**os.environ, "SRD_URL": server.url, "SRD_DATA_DIR": str(data_dir)}
        env.pop("SRD_ADMIN_TOKEN", None)
        run = run_block(quick_start_block(), ROOT, env)
        lines = run.stdout.splitlines()
        assert lines[:5] == ["true"] * 5 and lines[6] == "2"  # verdicts, then version 2
        rules = {reason["rule"] for reason in json.loads(lines[5])}  # the saboteur's reasons
        assert "always-holds" in rules, lines[5]
        assert f"{server.url}/ui/#/auctions/1" in run.stdout
        assert "iteration 0: price 5.000" in run.stdout  # srd watch, line by line
        assert "auction 1 finished" in run.stdout
        buyers = json.loads(lines[-1])
        with httpx.Client(base_url=server.url) as api:
            auction = api.get("/auctions/1").json()
            assert auction["status"] == "finished" and auction["n_patrons"] == 6
            assert auction["fine_tune_mode"] == "remote" and auction["fine_tuning"]
            assert buyers == auction["buyers"]
            assert len(buyers) == auction["n_initial"] == 3  # every fish sold
            saboteur = api.get("/models", params={"accepted": "false"}).json()["items"]
            assert [m["participant"] for m in saboteur] == ["saboteur-1"]
            assert api.get("/participants/honest-1").json()["n_versions"] == 2
            assert api.get("/ui/").status_code == 200  # the page the block points at


@pytest.mark.slow  # docs/remote.md's walk-through; the README's quick start runs by default
def test_remote_step_by_step_runs_as_pasted(tmp_path: Path) -> None:
    """docs/remote.md's curl walkthrough, on a fresh server: the upload is accepted."""
    text = (ROOT / "docs" / "remote.md").read_text()
    section = text.split("\n## Taking part, step by step with curl\n", 1)[1].split("\n## ", 1)[0]
    [block] = re.findall(r"```sh\n(.*?)```", section, flags=re.DOTALL)
    for name in (".venv", "examples"):  # its files land in the folder it runs in, not here
        (tmp_path / name).symlink_to(ROOT / name)
    data_dir = tmp_path / "data"
    server = ServerProcess(database_url=f"sqlite:///{tmp_path / 'srd.db'}", data_dir=data_dir)
    with server:
        env = {**os.environ, "SRD_URL": server.url, "SRD_DATA_DIR": str(data_dir)}
        env.pop("SRD_ADMIN_TOKEN", None)
        run_block(block, tmp_path, env)
        with httpx.Client(base_url=server.url) as api:
            auction = api.get("/auctions/1").json()
            [round_1] = auction["fine_tuning"]
            [answer] = [a for a in round_1["answers"] if a["model_id"] == 1]
            assert answer["outcome"] == "accepted" and answer["version"] == 2, answer


@pytest.mark.parametrize("path", ["README.md", "docs/web.md"])
def test_docs_link_to_pages_that_exist(path: str) -> None:
    text = (ROOT / path).read_text()
    for target in re.findall(r"\]\(((?:docs/)?[\w/.-]+\.(?:md|png))\)", text):
        base = ROOT if path == "README.md" else ROOT / "docs"
        assert (base / target).exists(), f"{path} links to a missing {target}"
