"""A PostgreSQL outage under a running ``srd serve``: requests get the JSON 503 with
``Retry-After`` meanwhile, writes resume by themselves within seconds once the database is
back, and every submission acknowledged before, during and after is stored.

The database server stopped here is a private throw-away cluster on a free port (never the
machine's shared one, which other tests use at the same time)."""

from __future__ import annotations

import glob
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path

import httpx
import pytest
from sqlalchemy import create_engine, text
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as ws_connect

from agents.manifest import parse_manifest
from agents.remote.fine_tuners import RoundInfo, faithful_fine_tune
from server.api.readiness import CACHE_S
from server.cli.launch import ServerProcess, free_port, settings_environment
from server.store.db import DATABASE_RETRY_AFTER_S, READ_TIMEOUT_S
from tests.server.test_remote_protocol import open_round, put, start_remote
from tests.support.factories import honest, unique
from tests.support.server import ADMIN, ADMIN_TOKEN, QUOTAS_OFF

pytestmark = pytest.mark.postgres

OUTAGE_S = 5.0
HIDDEN_ROUND_S = 5.0
"""The deadline of a round opened just before the outage: it passes while the database is
away."""
SPENT_S = 2.5  # of the round's time, spent before the outage
RESUME_WITHIN_S = 5.0  # writes answer 201 again this soon after the database is back
DB_NAME = "srd_outage"


@dataclass
class Cluster:
    """A PostgreSQL cluster of our own, run by the ``postgres`` user."""

    bin_dir: Path
    data: Path
    port: int

    def _ctl(self, *args: str) -> None:
        subprocess.run(
            ["runuser", "-u", "postgres", "--", str(self.bin_dir / "pg_ctl"), "-D", str(self.data),
             *args],
            check=True, capture_output=True, timeout=60,
        )  # fmt: skip

    def start(self) -> None:
        options = f"-p {self.port} -c listen_addresses=127.0.0.1 -k {self.data}"
        self._ctl("-o", options, "-l", str(self.data / "server.log"), "-w", "start")

    def stop(self) -> None:
        self._ctl("-m", "fast", "-w", "stop")

    @property
    def admin_url(self) -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"


@pytest.fixture
def cluster() -> Iterator[Cluster]:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
    if not found or shutil.which("runuser") is None:
        pytest.skip("no PostgreSQL server binaries (/usr/lib/postgresql/*/bin) or no runuser")
    bin_dir = Path(found[-1]).parent
    root = Path(tempfile.mkdtemp(prefix="srd-pg-"))  # /tmp: the postgres user can reach it
    shutil.chown(root, "postgres")
    data = root / "data"
    subprocess.run(
        ["runuser", "-u", "postgres", "--", str(bin_dir / "initdb"), "-D", str(data),
         "-A", "trust", "-U", "postgres", "--no-sync"],
        check=True, capture_output=True, timeout=120,
    )  # fmt: skip
    server = Cluster(bin_dir, data, free_port())
    server.start()
    try:
        engine = create_engine(server.admin_url, isolation_level="AUTOCOMMIT")
        with engine.connect() as connection:
            connection.execute(text(f"CREATE DATABASE {DB_NAME}"))
        engine.dispose()
        yield server
    finally:
        subprocess.run(
            ["runuser", "-u", "postgres", "--", str(bin_dir / "pg_ctl"), "-D", str(data),
             "-m", "immediate", "stop"],
            capture_output=True, timeout=60,
        )  # fmt: skip
        shutil.rmtree(root, ignore_errors=True)


def assert_unavailable(response: httpx.Response) -> None:
    """The JSON 503 of a database outage, with when to try again."""
    assert response.status_code == 503, response.text
    assert response.headers["content-type"] == "application/json"
    assert int(response.headers["retry-after"]) > 0
    [item] = response.json()["detail"]
    assert item["loc"] == ["database"] and item["type"] == "db_unavailable"
    assert "127.0.0.1" not in response.text and "psycopg" not in response.text  # log only


def lease_owner(url: str, auction_id: int) -> str | None:
    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            owner: str | None = connection.execute(
                text("SELECT lease_owner FROM auctions WHERE id = :id"), {"id": auction_id}
            ).scalar_one()
        return owner
    finally:
        engine.dispose()


def test_writes_resume_after_a_postgres_outage(cluster: Cluster, tmp_path: Path) -> None:
    password = "never-logged-9f3"  # trust authentication ignores it; the log must too
    url = f"postgresql+psycopg://postgres:{password}@127.0.0.1:{cluster.port}/{DB_NAME}"
    env = settings_environment({**QUOTAS_OFF, "lease_s": 3.0})
    stored: dict[str, int] = {}  # every participant acknowledged with 201, and its model id

    with (
        ServerProcess(
            database_url=url, data_dir=tmp_path / "data", admin_token=ADMIN_TOKEN, extra_env=env
        ) as server,
        ServerProcess(  # a second replica, which meets the same outage
            database_url=url,
            data_dir=tmp_path / "data",
            admin_token=ADMIN_TOKEN,
            extra_env=env,
            log_path=tmp_path / "replica.log",
        ) as replica,
        httpx.Client(base_url=server.url, timeout=30) as client,
        httpx.Client(base_url=replica.url, timeout=30) as replica_client,
    ):

        def submit(tag: str) -> httpx.Response:
            name = unique(tag)
            response = client.post("/submit", json=honest(name))
            assert response.status_code in (201, 503), response.text  # never a 500
            if response.status_code == 201:
                stored[name] = response.json()["model_id"]
            else:
                assert_unavailable(response)
            return response

        for _ in range(3):
            assert submit("before").status_code == 201
        # A remote round opens just before the outage, with less time than the outage lasts.
        auction_id, manifests, patrons = start_remote(
            client, "hidden-round", 730, 4, round_deadline_s=HIDDEN_ROUND_S, seed=5
        )
        state = open_round(client, auction_id)
        read_at = time.monotonic()
        assert state["status"] == "open" and state["round"] == 1, state
        [hearer, *_] = [p for p, (m, _) in enumerate(patrons) if m in state["asked"]]
        body = faithful_fine_tune(
            parse_manifest(manifests[hearer]), RoundInfo.from_state(state, hearer)
        ).model_dump_json()

        time.sleep(SPENT_S - (time.monotonic() - read_at))
        stopping = time.monotonic()
        for each in (client, replica_client):  # both replicas' last answer: the outage's start
            assert each.get(f"/models/{stored[next(iter(stored))]}").status_code == 200
        left_at_stop = state["seconds_left"] - (stopping - read_at)  # at most, for either
        cluster.stop()
        outage_began = time.monotonic()
        left_at_outage = state["seconds_left"] - (outage_began - read_at)
        time.sleep(CACHE_S)  # /healthz may repeat its last answer for this long
        stopped_at = time.monotonic()
        outage_answers = 0
        while time.monotonic() - stopped_at < OUTAGE_S:
            if submit("during").status_code == 503:
                outage_answers += 1
            assert_unavailable(client.get("/models/1"))
            assert_unavailable(client.get("/auctions/1/events"))
            assert_unavailable(client.get("/jobs/1/events"))
            health = client.get("/healthz")
            assert health.status_code == 503 and health.headers["retry-after"]
            assert health.json()["status"] == "unavailable"
            assert [p["check"] for p in health.json()["problems"]] == ["database"]
            assert "127.0.0.1" not in health.text and "psycopg" not in health.text
            assert client.get("/livez").json() == {"status": "ok"}
            time.sleep(0.2)
        assert outage_answers > 5
        log = server.log_path.read_text()
        assert f"port {cluster.port} failed" in log  # the cause, in the log only
        assert password not in log and "postgres:***@127.0.0.1" in log

        cluster.start()
        back_at = time.monotonic()
        while submit("after").status_code != 201:
            assert time.monotonic() - back_at < RESUME_WITHIN_S, "writes did not resume"
            time.sleep(0.1)
        resumed_s = time.monotonic() - back_at

        # The round's deadline passed during the outage, which hid the round from whoever
        # had not heard of it yet: it got back the time it had left when the outage began.
        current = f"/auctions/{auction_id}/rounds/current"
        while (now := client.get(current).json())["seconds_left"] == 0:  # the runner's next pass
            assert time.monotonic() - back_at < RESUME_WITHIN_S, f"never pushed back: {now}"
            time.sleep(0.1)
        assert now["round"] == 1 and now["status"] == "open", now
        assert now["seconds_left"] > left_at_outage - (time.monotonic() - back_at) - 0.5, now
        # Both replicas met the outage; the time is given back once, not once by each.
        logs = (server.log_path, replica.log_path)
        while not all(
            "get the time they had left back" in log.read_text()
            or "given their time back by another replica" in log.read_text()
            for log in logs
        ):
            assert time.monotonic() - back_at < RESUME_WITHIN_S + 3, "a replica never looked"
            time.sleep(0.1)
        now = client.get(current).json()
        assert now["seconds_left"] < left_at_stop + DATABASE_RETRY_AFTER_S + 1.0, now
        model_id, token = patrons[hearer]
        answer = put(client, auction_id, 1, model_id, body.encode(), token)
        assert answer.status_code == 200 and answer.json()["outcome"] == "accepted", answer.text
        [round_1] = client.get(f"/auctions/{auction_id}").json()["fine_tuning"]
        assert datetime.fromisoformat(round_1["deadline"]) > datetime.fromisoformat(
            state["deadline"]
        ) + timedelta(seconds=OUTAGE_S), round_1
        assert any("get the time they had left back" in log.read_text() for log in logs)

        for _ in range(3):
            assert submit("after").status_code == 201
        # Readiness answers are kept a second (and so are database checks): it may still
        # report the outage for that long after the first write went through.
        while client.get("/healthz").json()["status"] != "ok":
            assert time.monotonic() - back_at < RESUME_WITHIN_S + 3, "never ready again"
            time.sleep(0.1)

        # The lease runner outlived the outage: it claims a new auction (takes its lease).
        created = client.post("/auctions", json={"n_fish": 1, "seed": 1}, headers=ADMIN)
        assert created.status_code == 201, created.text
        deadline = time.monotonic() + 10
        while lease_owner(url, created.json()["auction_id"]) is None:
            assert time.monotonic() < deadline, "no auction was claimed after the outage"
            time.sleep(0.1)

        for name, model_id in stored.items():
            model = client.get(f"/models/{model_id}")
            assert model.status_code == 200 and model.json()["participant"] == name

    print(f"writes resumed {resumed_s:.2f} s after PostgreSQL was back; {len(stored)} stored")
    assert len(stored) >= 7


@contextmanager
def serving(
    cluster: Cluster, tmp_path: Path, *, timeout_s: float
) -> Iterator[tuple[ServerProcess, httpx.Client]]:
    """``srd serve`` on the cluster's database (leases of 3 s, quotas off), and a client."""
    url = f"postgresql+psycopg://postgres@127.0.0.1:{cluster.port}/{DB_NAME}"
    env = settings_environment({**QUOTAS_OFF, "lease_s": 3.0})
    with (
        ServerProcess(
            database_url=url, data_dir=tmp_path / "data", admin_token=ADMIN_TOKEN, extra_env=env
        ) as server,
        httpx.Client(base_url=server.url, timeout=timeout_s) as client,
    ):
        yield server, client


def cluster_pids(cluster: Cluster) -> list[int]:
    """The postmaster and every process it runs."""
    postmaster = int((cluster.data / "postmaster.pid").read_text().split()[0])
    children = subprocess.run(
        ["pgrep", "-P", str(postmaster)], capture_output=True, text=True, timeout=10
    ).stdout.split()
    return [postmaster, *map(int, children)]


def timed(call: Callable[[], httpx.Response]) -> tuple[httpx.Response, float]:
    started = time.monotonic()
    response = call()
    return response, time.monotonic() - started


HUNG_S = 8.0
HANG_TRIES = 40
ANSWER_WITHIN_S = READ_TIMEOUT_S + 3  # a read the database never answers is refused by then


@pytest.mark.slow  # 30 s of hangs; the default run keeps test_writes_resume_after_a_postgres_outage
def test_a_hung_or_stopped_postgres_holds_no_request_and_serves_no_stale_round(
    cluster: Cluster, tmp_path: Path
) -> None:
    """A database that keeps its connections but answers nothing (every PostgreSQL process
    stopped with SIGSTOP, as a host cut off without a word looks): every request is answered,
    /healthz says not ready, and nothing a round socket or a long poll holds in memory is served
    as current. Then a clean stop: the round a socket watches is 503 for anyone else too.
    First, brief hangs right after reads: the server answers through each."""
    with serving(cluster, tmp_path, timeout_s=60) as (server, client):
        # The database hangs right after it answered a read, while the server may still have
        # to end that read's transaction (its rollback goes out after the response): the
        # server goes on answering. It had closed the session on its event loop, so a hang in
        # that instant froze every request (about one try in five) until the database woke.
        for _ in range(HANG_TRIES):
            pids = cluster_pids(cluster)
            assert client.get("/models").status_code == 200
            for pid in pids:
                os.kill(pid, signal.SIGSTOP)
            try:
                response, took = timed(lambda: client.get("/livez", timeout=ANSWER_WITHIN_S))
                assert response.status_code == 200 and took < 2, took
            finally:
                for pid in pids:
                    os.kill(pid, signal.SIGCONT)

        auction_id, _, _ = start_remote(client, "hung", 700, 4, round_deadline_s=120, seed=3)
        assert open_round(client, auction_id)["status"] == "open"
        current = f"/auctions/{auction_id}/rounds/current"
        socket_url = (
            server.url.replace("http://", "ws://") + f"/auctions/{auction_id}/rounds/socket"
        )
        with ws_connect(socket_url) as socket:  # the round's snapshot is held in memory
            assert json.loads(socket.recv(timeout=10))["body"]["status"] == "open"
            pids = cluster_pids(cluster)
            assert client.get("/models").status_code == 200  # the database check is fresh
            for pid in pids:
                os.kill(pid, signal.SIGSTOP)
            try:
                # a read on a pooled connection, before the check notices: 503 in time, and
                # its session is closed only once the database answers (no 500 from closing it)
                response, took = timed(lambda: client.get("/models"))
                assert took < ANSWER_WITHIN_S
                assert_unavailable(response)
                hung_at, refused = time.monotonic(), set()
                while time.monotonic() - hung_at < HUNG_S:
                    for path in ("/healthz", f"/auctions/{auction_id}", current, "/models"):
                        response, took = timed(lambda p=path: client.get(p))  # type: ignore[misc]
                        assert took < ANSWER_WITHIN_S, (path, took)
                        assert response.status_code in (200, 503), response.text
                        if response.status_code == 503:
                            assert response.headers["content-type"] == "application/json"
                            refused.add(path)
                    time.sleep(0.2)
                assert {"/healthz", current} <= refused, refused
                with pytest.raises(ConnectionClosed) as closed:  # told to reconnect
                    while True:
                        socket.recv(timeout=ANSWER_WITHIN_S)
                assert closed.value.rcvd is not None and closed.value.rcvd.code == 1011
            finally:
                for pid in pids:
                    os.kill(pid, signal.SIGCONT)

        deadline = time.monotonic() + 20
        while client.get("/healthz").status_code != 200:
            assert time.monotonic() < deadline, "never ready after the database answered again"
            time.sleep(0.2)
        with ws_connect(socket_url) as socket:
            assert json.loads(socket.recv(timeout=10))["body"]["status"] == "open"
            assert client.get(current).status_code == 200
            cluster.stop()
            time.sleep(CACHE_S)
            response, took = timed(lambda: client.get(current))  # another client, same round
            assert_unavailable(response)
            with pytest.raises(ConnectionClosed) as closed:
                while True:
                    socket.recv(timeout=10)
            assert closed.value.rcvd is not None and closed.value.rcvd.code == 1011
        cluster.start()


ROUND_S = 9.0
"""The round's deadline: long enough to open it and fine-tune, short enough to wait out."""
BEFORE_S = 1.2
"""The database stops this long before the round's deadline (stopping it takes a moment: up to
0.75 s seen with three test processes busy), and stays stopped past it."""
RETRY_AFTER_S = 4.5
"""An agent's retry comes this long after the database is back: after the deadline the outage
pushed back (the 1.2 s at most the round had left when the outage began, plus the 503's
Retry-After of 2 s, from the lease runner's first pass, within half a second), before the grace
after an outage (5 s) ends and a step closes the round."""


@pytest.mark.slow  # a round waited out around an outage (20 s): make test-all
def test_an_upload_an_outage_refused_before_the_deadline_counts_on_its_retry(
    cluster: Cluster, tmp_path: Path
) -> None:
    """An upload that reached the server in time but met a database outage (503) is judged by
    that first arrival when the agent sends the same bytes again once the database is back,
    after the deadline (pushed back by the outage): in time, and the round waits for it. An
    upload first sent after that deadline is late as ever."""
    with serving(cluster, tmp_path, timeout_s=30) as (_, client):
        auction_id, manifests, patrons = start_remote(
            client, "outage-round", 720, 4, round_deadline_s=ROUND_S, seed=4
        )
        state = open_round(client, auction_id)
        assert state["status"] == "open" and state["round"] == 1, state
        asked = [p for p, (m, _) in enumerate(patrons) if m in state["asked"]]
        assert len(asked) >= 2, state
        bodies = {
            p: faithful_fine_tune(parse_manifest(manifests[p]), RoundInfo.from_state(state, p))
            .model_dump_json()
            .encode()
            for p in asked[:2]
        }
        first, second = asked[:2]

        def upload(position: int) -> httpx.Response:
            model_id, token = patrons[position]
            return put(client, auction_id, 1, model_id, bodies[position], token)

        left = client.get(f"/auctions/{auction_id}/rounds/current").json()["seconds_left"]
        deadline = time.monotonic() + left
        time.sleep(max(0.0, left - BEFORE_S))
        cluster.stop()
        assert time.monotonic() < deadline - 0.2, "the outage began too late to test"
        assert_unavailable(upload(first))  # in time, refused by the outage
        time.sleep(max(0.0, deadline + 1.0 - time.monotonic()))  # past it, still stopped
        cluster.start()
        back_at = time.monotonic()
        time.sleep(RETRY_AFTER_S)
        while (answer := upload(first)).status_code == 503:  # the agent's retry
            assert time.monotonic() - back_at < RESUME_WITHIN_S, "writes did not resume"
            time.sleep(0.5)
        assert answer.status_code == 200, answer.text
        assert answer.json()["outcome"] == "accepted", answer.text
        # The deadline as pushed back (from the runner's pass once the database answered: on
        # a busy machine that pass comes later, and the second upload was then in time).
        left = client.get(f"/auctions/{auction_id}/rounds/current").json()["seconds_left"]
        time.sleep(left + 0.1)
        late = upload(second)  # first sent after the deadline
        assert late.status_code == 410, late.text
        closed = open_round(client, auction_id, after=1)
        assert closed["auction_status"] in ("running", "finished") or closed["round"] == 2
        auction = client.get(f"/auctions/{auction_id}").json()
        [round_1] = [r for r in auction["fine_tuning"] if r["round"] == 1]
        outcomes = {a["model_id"]: a["outcome"] for a in round_1["answers"]}
        assert outcomes[patrons[first][0]] == "accepted", round_1
        assert outcomes[patrons[second][0]] == "late", round_1
