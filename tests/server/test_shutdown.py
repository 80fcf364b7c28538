"""A graceful stop of ``srd serve`` (SIGTERM) does not wait out its long polls: an agent
waiting for the next round is answered at once with the current state, an agent on a round
socket is told to reconnect (close code 1012, service restart), an event stream ends (its
client resumes from its last id), and the server exits well within uvicorn's graceful-shutdown
timeout (10 s)."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import httpx
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from server.cli.launch import ServerProcess, free_port, srd_command
from tests.support.factories import honest, unique
from tests.support.live import create_unstarted_auction
from tests.support.server import wait_for

ADMIN_TOKEN = "shutdown-admin-token-0123456789"
ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}

WAIT_S = 30  # the longest wait a long poll may ask: far longer than the stop may take


def test_sigterm_answers_waiting_long_polls_and_exits_promptly(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    with ServerProcess(database_url=url, data_dir=tmp_path / "data") as server:
        ids = [
            httpx.post(server.url + "/submit", json=honest(unique("stop")), timeout=60).json()[
                "model_id"
            ]
            for _ in range(2)
        ]
        auction_id = create_unstarted_auction(url, ids, n_fish=1, seed=1)  # it never opens
        answers: list[httpx.Response] = []

        def wait_for_a_round() -> None:
            answers.append(
                httpx.get(
                    f"{server.url}/auctions/{auction_id}/rounds/current",
                    params={"wait": WAIT_S},
                    timeout=WAIT_S + 30,
                )
            )

        closes: list[int | None] = []
        listening = threading.Event()

        async def listen_on_a_socket() -> None:
            socket_url = f"ws://127.0.0.1:{server.port}/auctions/{auction_id}/rounds/socket"
            async with connect(socket_url) as ws:
                await ws.recv()  # the first state: no round yet
                listening.set()
                try:
                    await asyncio.wait_for(ws.recv(), WAIT_S)
                except ConnectionClosed as closed:
                    closes.append(closed.rcvd.code if closed.rcvd else None)

        streams: list[str] = []

        def follow_the_events() -> None:
            url = f"{server.url}/auctions/{auction_id}/events"
            with httpx.stream("GET", url, timeout=WAIT_S + 30) as stream:
                streams.append("".join(stream.iter_text()))  # to its end

        waiters = [threading.Thread(target=wait_for_a_round) for _ in range(3)]
        waiters.append(threading.Thread(target=follow_the_events))
        waiters.append(threading.Thread(target=lambda: asyncio.run(listen_on_a_socket())))
        for waiter in waiters:
            waiter.start()
        assert listening.wait(30)  # the socket is served (the polls, sent first, wait too)
        time.sleep(1.0)
        assert not answers
        stopping = time.monotonic()
        server.stop()
        took = time.monotonic() - stopping
        for waiter in waiters:
            waiter.join(timeout=30)
    assert took < 7.0, f"the stop took {took:.1f} s"  # uvicorn alone waited its 10 s
    assert [a.status_code for a in answers] == [200, 200, 200]
    assert {a.json()["status"] for a in answers} == {"none"}
    assert closes == [1012]
    assert len(streams) == 1 and "event: end" not in streams[0]  # cut short, not ended
    assert "timeout graceful shutdown exceeded" not in (tmp_path / "data" / "serve.log").read_text()


@pytest.mark.parametrize(
    "sig",
    # Both run in `make test-all` (33 s each): the default run's ten minutes are short of room;
    # it keeps a kill -9 that requeues the running job (test_restart.py) and SIGTERM's answer
    # to waiting long polls.
    [
        pytest.param(signal.SIGINT, marks=pytest.mark.slow),
        pytest.param(signal.SIGTERM, marks=pytest.mark.slow),
    ],
)
def test_a_signal_to_the_whole_process_group_requeues_the_running_job(
    tmp_path: Path, sig: signal.Signals
) -> None:
    """Ctrl-C in a terminal (SIGINT), ``timeout`` or a service manager (SIGTERM) signal every
    process of the server's group: the job running then goes back to the queue, as with a
    signal to the server alone. Before, its worker died at once and the job was failed
    ("the job worker exited (code 1) without a result")."""
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    port = free_port()
    env = {**os.environ, "SRD_DATABASE_URL": url, "SRD_DATA_DIR": str(tmp_path / "data"),
           "SRD_ADMIN_TOKEN": ADMIN_TOKEN}  # fmt: skip
    command = [*srd_command(), "serve", "--host", "127.0.0.1", "--port", str(port)]
    base = f"http://127.0.0.1:{port}"
    with (tmp_path / "serve.log").open("ab") as log:
        server = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT,
                                  start_new_session=True)  # fmt: skip
        try:
            wait_for(lambda: _healthy(base), bool, 120)
            job = {"kind": "fish", "params": {"steps": 2_000_000}}  # minutes: it is stopped
            created = httpx.post(f"{base}/jobs", json=job, headers=ADMIN, timeout=30)
            job_id = created.json()["job_id"]
            wait_for(lambda: httpx.get(f"{base}/jobs/{job_id}").json(),
                     lambda j: j["status"] == "running" and j["progress"] > 0, 120)  # fmt: skip
            os.killpg(server.pid, sig)
            server.wait(30)  # uvicorn ends by raising the signal again: its code is -sig
        finally:
            if server.poll() is None:
                os.killpg(server.pid, signal.SIGKILL)
                server.wait()
    with ServerProcess(database_url=url, data_dir=tmp_path / "data",
                       admin_token=ADMIN_TOKEN) as again:  # fmt: skip
        state = httpx.get(f"{again.url}/jobs/{job_id}", timeout=30).json()
        assert state["status"] in ("queued", "running"), state
        cancelled = httpx.delete(f"{again.url}/jobs/{job_id}", headers=ADMIN, timeout=30)
        assert cancelled.status_code == 200  # (httpx's 5 s timed out under a loaded machine)


def _healthy(base: str) -> bool:
    try:
        return httpx.get(f"{base}/healthz", timeout=1).status_code == 200
    except httpx.TransportError:
        return False


@pytest.mark.slow  # the default run keeps its neighbours (docs/development.md)
def test_sigint_to_a_background_server_exits_130(tmp_path: Path) -> None:
    """A shell starts a background job with SIGINT ignored; uvicorn stops on it all the same and
    then raises it again, which was ignored too: the server exited 0, not 130 as for Ctrl-C."""
    port = free_port()
    env = {**os.environ, "SRD_DATABASE_URL": f"sqlite:///{tmp_path / 'srd.db'}",
           "SRD_DATA_DIR": str(tmp_path / "data"), "SRD_ADMIN_TOKEN": ADMIN_TOKEN}  # fmt: skip
    command = [*srd_command(), "serve", "--host", "127.0.0.1", "--port", str(port)]
    server = subprocess.Popen(
        command,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    try:
        wait_for(lambda: _healthy(f"http://127.0.0.1:{port}"), bool, 120)
        server.send_signal(signal.SIGINT)
        out, _ = server.communicate(timeout=60)
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()
    assert server.returncode == 130, out.decode()[-2000:]
    assert b"Aborted!" in out
