"""Property-based API check: schemathesis drives the live server from its /openapi.json.

Checks: no 5xx, every status code documented, content types, headers and bodies match the
schema. Slow (about a minute): run with ``pytest -m slow tests/server/test_schemathesis.py``.
"""

from __future__ import annotations

import secrets
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from server.launch import ServerProcess

CHECKS = (
    "not_a_server_error",
    "status_code_conformance",
    "content_type_conformance",
    "response_headers_conformance",
    "response_schema_conformance",
)


@pytest.mark.slow
def test_schemathesis_finds_no_server_error_and_no_schema_mismatch(tmp_path: Path) -> None:
    binary = Path(sys.executable).with_name("schemathesis")
    command = str(binary) if binary.exists() else shutil.which("schemathesis")
    if command is None:
        pytest.skip("schemathesis is not installed (pip install -e '.[dev]')")
    token = secrets.token_hex(16)
    server = ServerProcess(
        database_url=f"sqlite:///{tmp_path / 'srd.db'}", data_dir=tmp_path, admin_token=token
    )
    with server:
        run = subprocess.run(
            [
                command,
                "run",
                f"{server.url}/openapi.json",
                "--header",
                f"Authorization: Bearer {token}",
                "--checks",
                ",".join(CHECKS),
                "--max-examples",
                "30",
                "--seed",
                "1",
            ],
            capture_output=True,
            text=True,
            timeout=900,
            check=False,
        )
    log = server.log_path.read_text()
    assert run.returncode == 0, run.stdout[-6000:]
    assert "passed" in run.stdout and "failed" not in run.stdout.rsplit("SUMMARY", 1)[-1]
    assert '" 500 ' not in log and "Traceback" not in log
