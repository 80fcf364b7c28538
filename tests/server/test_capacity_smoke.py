"""The capacity benchmark at a tiny size: one real ``srd serve``, 8 agents in one auction over
both transports; its report has every field and every upload was answered."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow  # a benchmark run (about 26 s): `make test-all`
FIELDS = {
    "transport",
    "agents",
    "auctions",
    "asked",
    "uploads",
    "errors",
    "upload_p50_ms",
    "upload_p99_ms",
    "close_p50_ms",
    "close_p95_ms",
    "close_max_ms",
    "next_round_p50_ms",
    "next_round_p95_ms",
    "server_cpu_ms_per_upload",
    "screening_cpu_ms_per_upload",
    "cpu_ms_per_upload_by_process",
    "load_average",
    "budgets",
}


def test_capacity_smoke(tmp_path: Path) -> None:
    command = [
        sys.executable,
        str(REPOSITORY / "benchmarks" / "capacity.py"),
        *("--agents", "8", "--transports", "websocket,http", "--rounds", "2"),
        *("--iterations", "3", "--think", "0,0.05", "--out", str(tmp_path)),
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((tmp_path / "capacity.json").read_text())
    assert report["plan"]["rounds"] == 2 and report["replicas"] == 1
    assert [(r["transport"], r["agents"]) for r in report["results"]] == [
        ("websocket", 8),
        ("http", 8),
    ]
    for result in report["results"]:
        assert result.keys() >= FIELDS
        assert result["auctions"] == 1
        # Every asked patron's upload was answered: none unanswered, missing or late.
        assert result["errors"] == 0, result["error_kinds"]
        assert result["uploads"] == result["asked"] >= 8
        assert result["accepted"] + result["refused"] == result["uploads"]
        assert result["accepted"] > 0
        assert 0 < result["upload_p50_ms"] <= result["upload_p99_ms"] < 60_000
        assert result["rounds_closed"] >= 1
        # With 2 rounds the second follows the first: told after the first's last answer.
        assert 0 < result["next_round_p50_ms"] <= result["next_round_p95_ms"] < 60_000
        assert result["server_cpu_ms_per_upload"] > 0
        assert result["screening_cpu_ms_per_upload"] > 0
        assert "srd-screening" in result["cpu_ms_per_upload_by_process"]
        assert set(result["budgets"]) == {"cpu_per_upload", "no_errors"}
    assert (tmp_path / "capacity.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = done.stdout.splitlines()
    assert table[0].split()[:2] == ["transport", "agents"]
    assert table[1].split()[:3] == ["websocket", "8", str(report["results"][0]["uploads"])]
