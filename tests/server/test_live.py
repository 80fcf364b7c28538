"""The live-update source: one batched read per change whatever the listeners (SQLite and
PostgreSQL), and on PostgreSQL the wake-up by ``NOTIFY`` of another process's commit, within
milliseconds, also after the listening connection was killed."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import create_engine, event, text, update
from sqlalchemy.orm import Session

from server.cli.launch import ServerProcess
from server.live.source import LISTENER_NAME, LiveSource
from server.store import crud
from server.store.db import Database, prepare_database
from server.store.tables import Job, utcnow
from tests.support.databases import postgres_database
from tests.support.live import (
    POPULATION,
    create_unstarted_auction,
    sse_events,
    submit_population,
)
from tests.support.server import ADMIN_TOKEN

LISTENERS = 20
WAKE_S = 0.2
"""How soon after another process's commit a long poll and a stream must have heard of it."""


def test_one_read_per_change_whatever_the_listeners(database_url: str, tmp_path: Path) -> None:
    """20 listeners of a job share one feed: it is built once per change of the job, and every
    read of the watched rows is one query per kind (three jobs, two auctions: two queries). On
    SQLite an interval in which nothing was committed reads nothing."""
    prepare_database(database_url, tmp_path / "databases.json")
    database = Database(database_url)
    with database.session(write=True) as session:
        jobs = [crud.create_job(session, kind="fish", params={}).id for _ in range(3)]
        session.commit()
    selects: list[str] = []

    def count(_conn: Any, _cursor: Any, statement: str, *_: Any) -> None:
        if statement.lstrip().upper().startswith("SELECT"):
            selects.append(statement)

    event.listen(database.engine, "before_cursor_execute", count)
    builds: list[str | None] = []

    def progress_view(_s: Session, _id: int, state: Any, _previous: Any) -> str | None:
        builds.append(None if state is None else state.message)
        return None if state is None else state.message

    def write(message: str, status: str = "running") -> None:
        with database.session(write=True) as session:
            session.execute(
                update(Job)
                .where(Job.id == jobs[0])
                .values(message=message, status=status, updated_at=utcnow())
            )
            crud.notify_change(session, kind="job", row_id=jobs[0])
            session.commit()

    def touch(job_id: int) -> None:
        with database.session(write=True) as session:
            session.execute(update(Job).where(Job.id == job_id).values(updated_at=utcnow()))
            session.commit()

    async def scenario() -> None:
        source = LiveSource(database, poll_s=0.02, safety_poll_s=0.5)

        async def listen() -> list[str | None]:
            seen: list[str | None] = []
            async with source.watch("job", jobs[0], progress_view) as feed:
                while feed.snapshot != "done":
                    if feed.snapshot not in seen:
                        seen.append(feed.snapshot)
                    await feed.wait(feed.generation, 5.0)
            return seen

        measured = asyncio.Event()

        async def idle(kind: crud.LiveKind, row_id: int) -> None:
            async with source.watch(kind, row_id, lambda *_: 0):
                await measured.wait()

        listeners = [asyncio.create_task(listen()) for _ in range(LISTENERS)]
        others = [asyncio.create_task(idle("job", j)) for j in jobs[1:]]
        others += [asyncio.create_task(idle("auction", a)) for a in (998_001, 998_002)]
        await asyncio.sleep(0.7)  # the first reads (of new feeds, after LISTEN) are done
        if source.listening:  # PostgreSQL: the safety poll reads while anyone listens
            reads, selects_before = await next_read(source, source.reads), len(selects)
            after = await next_read(source, reads + 1)
        else:  # SQLite: a poll reads only if something was committed since the last read
            reads, selects_before = source.reads, len(selects)
            await asyncio.sleep(0.3)  # 15 intervals
            assert (source.reads, len(selects)) == (reads, selects_before)
            await asyncio.to_thread(touch, jobs[1])  # a commit: the next poll reads
            after = await next_read(source, reads)
        assert len(selects) - selects_before == 2 * (after - reads)  # one query per kind per read
        measured.set()
        for message in ("one", "two"):
            await asyncio.to_thread(write, message)
            await asyncio.sleep(0.1 if source.listening else 0.6)
        await asyncio.to_thread(write, "done", "succeeded")
        seen = await asyncio.gather(*listeners)
        await asyncio.gather(*others)
        assert all(s == ["queued", "one", "two"] for s in seen), seen
        assert builds == ["queued", "one", "two", "done"]  # one build per change, 20 listeners
        assert source.watched == 0
        await source.close()

    try:
        asyncio.run(scenario())
    finally:
        database.close()


@pytest.mark.postgres
def test_a_row_made_due_through_any_replica_wakes_every_runner(pg_url: str, tmp_path: Path) -> None:
    """On PostgreSQL a commit that makes work due (an auction or a job created, a round closed
    by its last verdict) says so on the channel, and every API process's live source wakes
    its runner of that kind: a replica whose workers are busy leaves the work to one with a
    free worker at once, not at its next pass (2 s). Heard without anyone watching a row."""
    prepare_database(pg_url, tmp_path / "databases.json")
    database = Database(pg_url)

    async def scenario() -> None:
        source = LiveSource(database, poll_s=0.02, safety_poll_s=30.0)
        woken = {"auction": asyncio.Event(), "job": asyncio.Event()}
        source.when_due("auction", woken["auction"].set)
        source.when_due("job", woken["job"].set)
        source.start()
        deadline = time.monotonic() + 10
        while not source.listening:
            assert time.monotonic() < deadline, "never listened"
            await asyncio.sleep(0.02)
        await asyncio.to_thread(create_unstarted_auction, pg_url, [], n_fish=1, seed=1)
        await asyncio.wait_for(woken["auction"].wait(), 5)
        assert not woken["job"].is_set()

        def new_job() -> None:
            with database.session(write=True) as session:
                crud.create_job(session, kind="fish", params={})
                session.commit()

        await asyncio.to_thread(new_job)
        await asyncio.wait_for(woken["job"].wait(), 5)
        assert source.watched == 0
        await source.close()

    try:
        asyncio.run(scenario())
    finally:
        database.close()


async def next_read(source: LiveSource, after: int) -> int:
    """``source.reads`` as soon as it passes ``after`` (before the next read can begin)."""
    deadline = time.monotonic() + 5
    while source.reads <= after:
        assert time.monotonic() < deadline, "the source stopped reading"
        await asyncio.sleep(0.001)
    return source.reads


# --- PostgreSQL: NOTIFY ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def pg_url() -> Iterator[str]:
    yield from postgres_database()


@pytest.fixture(scope="module")
def pg_server(pg_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    """A server whose safety poll is 30 s: anything it hears sooner came by NOTIFY."""
    env = {"SRD_LIVE_SAFETY_POLL_S": "30", "SRD_EVENT_KEEPALIVE_S": "30"}
    with ServerProcess(
        database_url=pg_url,
        data_dir=tmp_path_factory.mktemp("server"),
        admin_token=ADMIN_TOKEN,
        extra_env=env,
    ) as running:
        yield running


@pytest.fixture(scope="module")
def pg_client(pg_server: ServerProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=pg_server.url, timeout=httpx.Timeout(60.0)) as http:
        yield http


@pytest.fixture(scope="module")
def patrons(pg_client: httpx.Client) -> list[int]:
    answers = submit_population(pg_client)
    return [a["model_id"] for name, a in answers.items() if name.startswith("honest")]


def listener_pid(url: str) -> int | None:
    """The backend pid of the server's listening connection, if it is connected."""
    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            return connection.execute(
                text(
                    "SELECT pid FROM pg_stat_activity WHERE application_name = :name"
                    " AND datname = current_database()"
                ),
                {"name": LISTENER_NAME},
            ).scalar_one_or_none()
    finally:
        engine.dispose()


def wake_delays(client: httpx.Client, url: str, auction_id: int) -> tuple[float, float]:
    """Seconds from the commit of the auction's cancel, made here (another process than the
    server), to the answer of a long poll waiting on it and to the end event of its stream."""
    heard: dict[str, float] = {}
    stream_ready = threading.Event()

    def long_poll() -> None:
        answer = client.get(f"/auctions/{auction_id}/rounds/current", params={"wait": 20})
        heard["poll"] = time.monotonic()
        assert answer.status_code == 200 and answer.json()["auction_status"] == "cancelled"

    def stream() -> None:
        with client.stream("GET", f"/auctions/{auction_id}/events") as response:
            for item in sse_events(response):
                stream_ready.set()
                if item.get("event") == "end":
                    heard["stream"] = time.monotonic()
                    return

    threads = [threading.Thread(target=long_poll), threading.Thread(target=stream)]
    for thread in threads:
        thread.start()
    assert stream_ready.wait(10)
    time.sleep(0.5)  # the long poll is waiting by now
    database = Database(url)
    try:
        with database.session(write=True) as session:
            assert crud.cancel_auction(session, auction_id=auction_id)
            session.commit()
        committed = time.monotonic()
    finally:
        database.close()
    for thread in threads:
        thread.join(10)
    return heard["poll"] - committed, heard["stream"] - committed


@pytest.mark.postgres
def test_a_commit_elsewhere_wakes_long_polls_and_streams_at_once(
    pg_client: httpx.Client, pg_server: ServerProcess, patrons: list[int]
) -> None:
    auction_id = create_unstarted_auction(pg_server.database_url, patrons, n_fish=1, seed=0)
    poll_s, stream_s = wake_delays(pg_client, pg_server.database_url, auction_id)
    assert poll_s < WAKE_S and stream_s < WAKE_S, (poll_s, stream_s)


@pytest.mark.postgres
def test_the_listener_survives_its_connection_being_killed(
    pg_client: httpx.Client, pg_server: ServerProcess, patrons: list[int]
) -> None:
    url = pg_server.database_url
    auction_id = create_unstarted_auction(url, patrons, n_fish=1, seed=1)
    with pg_client.stream("GET", f"/auctions/{auction_id}/events") as response:
        next(sse_events(response))  # the server listens by now
    killed = listener_pid(url)
    assert killed is not None
    engine = create_engine(url)
    with engine.connect() as connection:
        assert connection.execute(text(f"SELECT pg_terminate_backend({killed})")).scalar()
    engine.dispose()
    deadline = time.monotonic() + 10
    while listener_pid(url) in (None, killed):
        assert time.monotonic() < deadline, "the listener did not reconnect"
        time.sleep(0.05)
    poll_s, stream_s = wake_delays(pg_client, url, auction_id)
    assert poll_s < WAKE_S and stream_s < WAKE_S, (poll_s, stream_s)


# --- SQLite: a step's commit -----------------------------------------------------------------


def test_sqlite_a_round_a_step_opens_reaches_long_polls_before_the_next_poll(
    tmp_path: Path,
) -> None:
    """On SQLite the API learns of a step's commits when the step ends, not at its next poll
    (10 s here): a long poll waiting for round 2 hears it soon after round 1's last answer."""
    env = {"SRD_EVENT_POLL_INTERVAL_S": "10", "SRD_EVENT_KEEPALIVE_S": "30"}
    with (
        ServerProcess(
            database_url=f"sqlite:///{tmp_path / 'steps.db'}",
            data_dir=tmp_path / "data",
            admin_token=ADMIN_TOKEN,
            extra_env=env,
        ) as server,
        httpx.Client(base_url=server.url, timeout=httpx.Timeout(60.0)) as client,
    ):
        answers = submit_population(client)
        honest = {a["model_id"]: (name, a["token"]) for name, a in answers.items()}
        honest = {k: v for k, v in honest.items() if v[0].startswith("honest")}
        body = {
            "n_fish": 1,
            "model_ids": list(honest),
            "fine_tune_mode": "remote",
            "fine_tune_rounds": 2,
            "round_deadline_s": 120,
        }
        created = client.post(
            "/auctions", json=body, headers={"Authorization": f"Bearer {ADMIN_TOKEN}"}
        )
        assert created.status_code == 201, created.text
        auction_id = created.json()["auction_id"]
        first = client.get(f"/auctions/{auction_id}/rounds/current", params={"wait": 20}).json()
        assert first["round"] == 1 and first["status"] == "open", first
        heard: dict[str, Any] = {}

        def long_poll() -> None:
            params = {"wait": 25, "after": 1}
            heard["state"] = client.get(f"/auctions/{auction_id}/rounds/current", params=params)
            heard["at"] = time.monotonic()

        waiter = threading.Thread(target=long_poll)
        waiter.start()
        time.sleep(0.5)  # the long poll is waiting by now
        for model_id in first["asked"]:  # each patron's current weights again: accepted at once
            name, token = honest[model_id]
            manifest = (POPULATION / f"{name}.json").read_bytes()
            put = client.put(
                f"/auctions/{auction_id}/rounds/1/models/{model_id}",
                content=manifest,
                headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
            )
            assert put.status_code == 200 and put.json()["accepted"], put.text
        answered = time.monotonic()
        waiter.join(30)
        state = heard["state"].json()
        assert state["round"] == 2 and state["status"] == "open", state
        assert heard["at"] - answered < 5, heard["at"] - answered  # not the 10 s poll
