"""Several API replicas on one PostgreSQL database, and SQLite's one server.

Two ``srd serve`` processes share a throw-away PostgreSQL database and a data folder. Auctions
and jobs created through either are each played exactly once (by whichever claims them first);
lists and event streams read the same through both; a job cancelled through one replica is
stopped by the other, which runs it; a remote round answered through both at once closes once,
on its answers; a round closed through a replica whose worker is held plays on at once on the
other. Killed with ``kill -9`` in the middle of an
auction, a replica loses its lease and the other resumes the auction from its checkpoint:
rounds contiguous, every purchase once, the same auction as one played uninterrupted. A second
server on a SQLite database refuses to start, saying why.
"""

from __future__ import annotations

import itertools
import signal
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import func, select

from agents.manifest import parse_manifest
from agents.remote import RoundInfo, faithful_fine_tune
from screener import screen
from server.cli.launch import ServerProcess, settings_environment
from server.store.db import Database
from server.store.tables import Auction, AuctionIteration, Job, Purchase
from sim.market import Market, MarketConfig
from tests.server.test_faults import signal_all, upload
from tests.support.databases import postgres_admin_url, throwaway_postgres
from tests.support.factories import honest
from tests.support.live import sse_events
from tests.support.processes import descendants, process_name, server_pair
from tests.support.remote import honest_remote_auction, next_round
from tests.support.server import ADMIN, ADMIN_TOKEN, QUOTAS_OFF, wait_for

LEASE_S = 2.0
"""Short leases: a dead replica's work moves within seconds."""
TIMEOUT_S = 240
KILLED_AUCTION = {"n_fish": 1, "fine_tune": True, "fine_tune_rounds": 20, "seed": 0}
ENV = settings_environment(
    {**QUOTAS_OFF, "lease_s": LEASE_S, "auction_workers": 1, "job_workers": 1}
)


@pytest.fixture
def postgres_url() -> Iterator[str]:
    admin_url = postgres_admin_url()
    if admin_url is None:
        pytest.skip("PostgreSQL is not reachable on 127.0.0.1:5432")
    with throwaway_postgres(admin_url) as url:
        yield url


def get(server: ServerProcess, path: str) -> Any:
    response = httpx.get(server.url + path, timeout=30)
    response.raise_for_status()
    return response.json()


def events(server: ServerProcess, path: str) -> list[dict[str, str]]:
    with httpx.stream("GET", server.url + path, timeout=60) as response:
        return [event for event in sse_events(response) if "event" in event]


def consistent(state: dict[str, Any]) -> dict[str, Any]:
    """An auction's state read while its steps commit, checked to be one state: its head, its
    history, its purchases and quits. PostgreSQL gives each statement of a transaction its own
    snapshot unless asked otherwise: a read had shown iteration 0 with one history row, or
    buyers its history did not hold yet."""
    history = state["history"]
    assert len(history) == state["iteration"], state
    moved = [b["iteration"] for b in state["buyers"]]
    moved += [q["iteration"] for q in state["quitter_details"]]
    assert all(i < len(history) for i in moved), state
    assert state["n_available"] == state["n_initial"] - len(state["buyers"]), state
    if history:
        assert history[-1]["n_available_after"] == state["n_available"], state
    return state


def alone(manifests: list[dict[str, Any]], config: MarketConfig) -> list[Any]:
    """The auction played uninterrupted, in this process."""
    market = Market(
        [parse_manifest(m) for m in manifests],
        config,
        rescreen=lambda _i, m: screen(m).accepted,
    )
    return list(market.run())


def lease_owner(database_url: str, table: type[Auction] | type[Job], row_id: int) -> str:
    database = Database(database_url)
    try:
        with database.session(write=False) as session:
            owner = session.scalar(select(table.lease_owner).where(table.id == row_id))
    finally:
        database.close()
    assert owner is not None
    return owner


def assert_played_once(
    auction: dict[str, Any], ids: list[int], records: list[Any], database: Database
) -> None:
    """Rounds contiguous and equal to the uninterrupted auction's, each purchase once."""
    assert auction["status"] == "finished", auction["error"]
    history = auction["history"]
    assert [row["iteration"] for row in history] == list(range(len(history)))
    assert [row["price"] for row in history] == [r.price for r in records]
    assert [row["votes"] for row in history] == [r.votes for r in records]
    assert [(b["model_id"], b["price"]) for b in auction["buyers"]] == [
        (ids[i], price) for r in records for i, price in r.buyers
    ]
    with database.session(write=False) as session:
        key = auction["id"]
        purchases = session.scalar(select(func.count()).where(Purchase.auction_id == key))
        rounds = session.scalar(select(func.count()).where(AuctionIteration.auction_id == key))
        lease = session.scalar(select(Auction.lease_owner).where(Auction.id == key))
    assert purchases == len(auction["buyers"]) and rounds == len(history)
    assert lease is None  # released once played


def submit_through_both(
    servers: Sequence[ServerProcess], manifests: list[dict[str, Any]]
) -> list[dict[str, Any]]:
    """The ``/submit`` answers of the manifests, submitted alternately through the replicas."""
    return [
        dict(httpx.post(servers[i % 2].url + "/submit", json=m, timeout=60).json())
        for i, m in enumerate(manifests)
    ]


def start_work(
    servers: Sequence[ServerProcess], admin: dict[str, str], ids: list[int]
) -> tuple[list[int], list[int]]:
    """Four auctions and two fish jobs, created alternately on the two replicas: their ids."""
    auctions = [
        httpx.post(
            servers[seed % 2].url + "/auctions",
            json={"n_fish": 2, "seed": seed, "model_ids": ids},
            headers=admin,
            timeout=60,
        ).json()["auction_id"]
        for seed in range(4)
    ]
    jobs = [
        httpx.post(
            servers[i].url + "/jobs",
            json={"kind": "fish", "params": {"steps": 30 + i}},
            headers=admin,
            timeout=60,
        ).json()["job_id"]
        for i in range(2)
    ]
    return auctions, jobs


def check_read_alike(
    servers: Sequence[ServerProcess], ids: list[int], auctions: list[int], jobs: list[int]
) -> None:
    """Lists, resources and event streams read the same from either replica."""
    for path in ("/auctions", "/jobs", "/models", f"/models/{ids[0]}"):
        assert get(servers[0], path) == get(servers[1], path), path
    for auction_id in auctions:
        assert get(servers[0], f"/auctions/{auction_id}") == get(
            servers[1], f"/auctions/{auction_id}"
        )
    stream = f"/auctions/{auctions[0]}/events"
    assert events(servers[0], stream) == events(servers[1], stream)
    stream = f"/jobs/{jobs[0]}/events"
    assert events(servers[0], stream)[-1] == events(servers[1], stream)[-1]


def check_cancel_reaches_the_playing_replica(
    servers: Sequence[ServerProcess], admin: dict[str, str], postgres_url: str
) -> None:
    """A job cancelled on one replica is stopped by the other, which runs it, at its next
    lease renewal."""
    long_job = httpx.post(
        servers[0].url + "/jobs",
        json={"kind": "fish", "params": {"steps": 1_000_000}},  # minutes: still running
        headers=admin,
        timeout=60,
    ).json()["job_id"]
    wait_for(
        lambda: get(servers[0], f"/jobs/{long_job}"),
        lambda j: j["status"] == "running",
        TIMEOUT_S,
    )
    owner = lease_owner(postgres_url, Job, long_job)
    playing = next(s for s in servers if s.process and f":{s.process.pid}:" in owner)
    other = next(s for s in servers if s is not playing)
    cancelled = httpx.delete(f"{other.url}/jobs/{long_job}", headers=admin, timeout=60)
    assert cancelled.json()["status"] == "cancelled"
    wait_for(  # the replica running it notices at its next lease renewal and stops it
        lambda: {"log": playing.log_path.read_text()},
        lambda s: f"job {long_job}: lease lost; stopped here" in s["log"],
        10 * LEASE_S,
    )


@pytest.mark.postgres
@pytest.mark.slow  # 38 s; the default run keeps the replica kill -9
def test_two_replicas_play_each_auction_and_job_once_and_read_alike(
    postgres_url: str, tmp_path: Path
) -> None:
    servers, admin = server_pair(postgres_url, tmp_path, ENV)
    manifests = [honest(f"replica-{i:02d}", seed=300 + i) for i in range(8)]
    try:
        for server in servers:
            server.start()
        ids = [answer["model_id"] for answer in submit_through_both(servers, manifests)]
        auctions, jobs = start_work(servers, admin, ids)
        done = [
            wait_for(
                lambda a=auction_id: consistent(get(servers[0], f"/auctions/{a}")),
                lambda a: a["status"] in ("finished", "failed"),
                TIMEOUT_S,
            )
            for auction_id in auctions
        ]
        finished_jobs = [
            wait_for(
                lambda j=job_id: get(servers[1], f"/jobs/{j}"),
                lambda j: j["status"] not in ("queued", "running"),
                TIMEOUT_S,
            )
            for job_id in jobs
        ]
        check_read_alike(servers, ids, auctions, jobs)
        check_cancel_reaches_the_playing_replica(servers, admin, postgres_url)
        artifact = f"/jobs/{jobs[1]}/artifacts/energy.csv"
        assert (
            httpx.get(servers[0].url + artifact).content
            == httpx.get(servers[1].url + artifact).content
        )
    finally:
        for server in servers:
            server.stop()
    database = Database(postgres_url)
    try:
        for auction, seed in zip(done, range(4), strict=True):
            assert_played_once(auction, ids, alone(manifests, MarketConfig(2, seed=seed)), database)
        with database.session(write=False) as session:
            attempts = [session.get(Job, job["id"]).attempt for job in finished_jobs]  # type: ignore[union-attr]
    finally:
        database.close()
    assert [job["status"] for job in finished_jobs] == ["succeeded", "succeeded"]
    assert attempts == [1, 1]  # each claimed once


@pytest.mark.postgres
def test_kill_9_of_the_replica_playing_an_auction_the_other_finishes_it(
    postgres_url: str, tmp_path: Path
) -> None:
    # the replay keeps what the screener accepts: no margin held for an inspector
    servers, admin = server_pair(postgres_url, tmp_path, {**ENV, "SRD_REVIEW_MARGIN": "0"})
    manifests = [honest(f"killed-{i:02d}", seed=200 + i) for i in range(64)]
    database = Database(postgres_url)
    try:
        for server in servers:
            server.start()
        with httpx.Client(base_url=servers[0].url, timeout=60) as client:
            ids = [client.post("/submit", json=m).json()["model_id"] for m in manifests]
            # fine-tuning after each of its first 20 rounds: seconds of rounds remain after
            # the first, so the kill comes mid-auction even on a busy machine
            body = {**KILLED_AUCTION, "model_ids": ids}
            created = client.post("/auctions", json=body, headers=admin)
            assert created.status_code == 201, created.text
            auction_id = created.json()["auction_id"]
        wait_for(
            lambda: get(servers[1], f"/auctions/{auction_id}"),
            lambda a: a["iteration"] >= 1,
            TIMEOUT_S,
        )
        owner = lease_owner(postgres_url, Auction, auction_id)
        playing = next(s for s in servers if s.process and f":{s.process.pid}:" in owner)
        survivor = next(s for s in servers if s is not playing)
        playing.kill()
        with database.session(write=False) as session:
            at_kill = session.scalars(select(Auction).where(Auction.id == auction_id)).one()
        assert at_kill.status == "running" and at_kill.iteration >= 1  # killed mid-auction
        auction = wait_for(
            lambda: get(survivor, f"/auctions/{auction_id}"),
            lambda a: a["status"] in ("finished", "failed"),
            TIMEOUT_S,
        )
        assert len(auction["history"]) > at_kill.iteration  # the survivor played on
        assert f"auction {auction_id} claimed by" in survivor.log_path.read_text()
        records = alone(manifests, MarketConfig(1, fine_tune=True, fine_tune_rounds=20, seed=0))
        assert_played_once(auction, ids, records, database)
    finally:
        for server in servers:
            server.stop()
        database.close()


@pytest.mark.postgres
@pytest.mark.slow  # 28 s; the default run keeps the replica kill -9 (its auction's rounds)
def test_a_remote_round_answered_through_both_replicas_at_once_closes_once(
    postgres_url: str, tmp_path: Path
) -> None:
    """Every patron of a remote auction uploads at once, half through each replica: the last
    verdicts of a round serialise on its row, so each round closes once, on its answers (long
    before its deadline), with every upload in it, and the auction plays on to its end."""
    servers, admin = server_pair(postgres_url, tmp_path, ENV)
    manifests = [honest(f"both-{i:02d}", seed=800 + i) for i in range(6)]
    try:
        for server in servers:
            server.start()
        answers = submit_through_both(servers, manifests)
        ids = [a["model_id"] for a in answers]
        tokens = {a["model_id"]: a["token"] for a in answers}
        body = {
            "n_fish": 2,
            "seed": 5,
            "model_ids": ids,
            "fine_tune_mode": "remote",
            "fine_tune_rounds": 2,
            "round_deadline_s": 120,
            "max_iterations": 12,
        }
        created = httpx.post(servers[0].url + "/auctions", json=body, headers=admin, timeout=60)
        assert created.status_code == 201, created.text
        auction_id = created.json()["auction_id"]

        def put(state: dict[str, Any], model_id: int) -> httpx.Response:
            position = ids.index(model_id)
            tuned = faithful_fine_tune(
                parse_manifest(manifests[position]), RoundInfo.from_state(state, position)
            )
            server = servers[position % 2]
            return httpx.put(
                f"{server.url}/auctions/{auction_id}/rounds/{state['round']}/models/{model_id}",
                content=tuned.model_dump_json(),
                headers={
                    "Authorization": f"Bearer {tokens[model_id]}",
                    "Content-Type": "application/json",
                },
                timeout=60,
            )

        after = 0
        while True:
            state = next_round(servers[after % 2], auction_id, after, TIMEOUT_S)
            if state["auction_status"] not in ("pending", "running"):
                break
            with ThreadPoolExecutor(len(state["asked"])) as pool:
                uploads = list(pool.map(lambda m, s=state: put(s, m), state["asked"]))
            assert all(u.status_code == 200 for u in uploads), [u.text for u in uploads]
            after = state["round"]
        auction = wait_for(
            lambda: get(servers[1], f"/auctions/{auction_id}"),
            lambda a: a["status"] not in ("pending", "running"),
            TIMEOUT_S,
        )
    finally:
        for server in servers:
            server.stop()
    assert auction["status"] == "finished" and auction["error"] is None
    rounds = auction["fine_tuning"]
    assert [r["round"] for r in rounds] == [1, 2], (auction["history"], auction["stop_reason"])
    for played in rounds:
        assert played["status"] == "closed" and played["closed_at"] < played["deadline"]
        assert {a["outcome"] for a in played["answers"]} <= {"accepted", "refused", "held"}
    assert after == 2


@pytest.mark.postgres
@pytest.mark.slow  # two replicas and a 64-round auction; the replica kill -9 runs by default
def test_a_round_closed_on_a_replica_with_no_free_worker_plays_on_at_once_on_the_other(
    postgres_url: str, tmp_path: Path
) -> None:
    """The replica a remote round is closed through has its one step worker held (stopped in
    a long auction it plays): the other, told that the auction is due, opens each next round
    at once, not at its next pass over the table (up to 2 s after the close)."""
    servers, admin = server_pair(postgres_url, tmp_path, {**ENV, "SRD_REVIEW_MARGIN": "0"})
    held: list[int] = []
    try:
        for server in servers:
            server.start()
        with httpx.Client(base_url=servers[0].url, timeout=60) as client:
            busy = [honest(f"busy-{i}", seed=300 + i) for i in range(8)]
            ids = [client.post("/submit", json=m).json()["model_id"] for m in busy]
            body = {**KILLED_AUCTION, "fine_tune_rounds": 64, "rows": 256, "model_ids": ids}
            long_id = client.post("/auctions", json=body, headers=admin).json()["auction_id"]
        owner = wait_for(
            lambda: {"owner": lease_owner_or_none(postgres_url, long_id)},
            lambda found: found["owner"] is not None,
            TIMEOUT_S,
        )["owner"]
        holder = next(s for s in servers if s.process and f":{s.process.pid}:" in owner)
        assert holder.process is not None
        pid = holder.process.pid
        held = wait_for(  # its worker process, started for the claim
            lambda: {"workers": step_workers(pid)}, lambda found: found["workers"], TIMEOUT_S
        )["workers"]
        signal_all(held, signal.SIGSTOP)
        auction_id, patrons = honest_remote_auction(
            holder, range(310, 314), name="due", n_fish=1, fine_tune_rounds=3, seed=3
        )
        manifests = {model_id: manifest for model_id, _, manifest in patrons}
        tokens = {model_id: token for model_id, token, _ in patrons}
        order = [model_id for model_id, _, _ in patrons]
        after = 0
        while (state := next_round(holder, auction_id, after, TIMEOUT_S))["status"] == "open":
            for model_id in state["asked"]:
                answer = upload(holder, auction_id, state, model_id, manifests, tokens, order)
                assert answer.status_code == 200, answer.text
            after = state["round"]
        rounds = get(holder, f"/auctions/{auction_id}")["fine_tuning"]
        assert len(rounds) >= 2, rounds
        gaps = [
            datetime.fromisoformat(b["opened_at"]) - datetime.fromisoformat(a["closed_at"])
            for a, b in itertools.pairwise(rounds)
        ]
        assert max(gap.total_seconds() for gap in gaps) < 1.0, gaps
    finally:
        signal_all(held, signal.SIGCONT)
        for server in servers:
            server.stop()


def step_workers(server_pid: int) -> list[int]:
    return [p for p in descendants(server_pid) if (process_name(p) or "").startswith("srd-auction")]


def lease_owner_or_none(database_url: str, auction_id: int) -> str | None:
    database = Database(database_url)
    try:
        with database.session(write=False) as session:
            return session.scalar(select(Auction.lease_owner).where(Auction.id == auction_id))
    finally:
        database.close()


def test_a_second_server_on_one_sqlite_database_refuses_to_start(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    first = ServerProcess(database_url=url, data_dir=tmp_path / "data", extra_env=ENV)
    second = ServerProcess(
        database_url=url,
        data_dir=tmp_path / "data",
        extra_env=ENV,
        log_path=tmp_path / "second.log",
    )
    try:
        first.start()
        with pytest.raises(RuntimeError, match="exited early"):
            second.start()
        log = second.log_path.read_text()
        assert first.process is not None
        assert f"another srd serve (pid {first.process.pid}) is serving the SQLite" in log
        assert "PostgreSQL" in log
        assert get(first, "/healthz")["status"] == "ok"
    finally:
        second.stop()
        first.stop()
    second.start()  # the lock goes with the server that held it
    second.stop()


@pytest.mark.postgres
@pytest.mark.slow  # 13 s; the default run's ten minutes are short of room
def test_a_replica_frozen_holding_a_lock_is_taken_over_when_its_lease_expires(
    postgres_url: str, tmp_path: Path
) -> None:
    """A replica frozen inside a transaction (a paused process or VM) keeps its row locks until
    its connection breaks, hours later while its host is up: the claim skips locked rows, so
    its auction stayed unplayed. Its lease's expiry is the sign that it is gone: the replica
    taking over ends the sessions named for that lease and plays the auction."""
    import psycopg
    from sqlalchemy import make_url

    from server.store.db import lease_session_name

    server = ServerProcess(
        database_url=postgres_url,
        data_dir=tmp_path / "data",
        admin_token=ADMIN_TOKEN,
        extra_env={**ENV, "SRD_REVIEW_MARGIN": "0"},
    )
    conninfo = make_url(postgres_url).set(drivername="postgresql")
    with server, httpx.Client(base_url=server.url, timeout=60) as client:
        ids = [
            client.post("/submit", json=honest(f"frozen-{i}", seed=300 + i)).json()["model_id"]
            for i in range(4)
        ]
        body = {"n_fish": 1, "max_iterations": 4, "model_ids": ids, "enrollment_s": 600}
        created = client.post("/auctions", json=body, headers=ADMIN)
        assert created.status_code == 201, created.text
        auction_id = created.json()["auction_id"]  # pending: due when its enrollment ends
        frozen = psycopg.connect(
            conninfo.render_as_string(hide_password=False),
            application_name=lease_session_name("frozen-replica"),
            autocommit=True,
        )
        try:  # the frozen replica's lease, due now, then its lock on the row, held
            frozen.execute(
                "UPDATE auctions SET lease_owner = 'frozen-replica', next_step_at = now(), "
                "lease_expires = now() + interval '2 seconds', enroll_until = now() "
                "WHERE id = %s",
                (auction_id,),
            )
            frozen.autocommit = False
            frozen.execute("SELECT id FROM auctions WHERE id = %s FOR UPDATE", (auction_id,))
            auction = wait_for(
                lambda: client.get(f"/auctions/{auction_id}").json(),
                lambda a: a["status"] in ("finished", "failed"),
                60,
            )
            assert auction["status"] == "finished", auction
            with pytest.raises(psycopg.OperationalError):  # its session was ended
                frozen.execute("SELECT 1")
        finally:
            frozen.close()
        assert "database sessions of frozen-replica" in server.log_path.read_text()
