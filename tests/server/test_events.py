"""The event streams against a real ``srd serve`` on loopback (an in-process transport cannot
end an endless stream), on SQLite and PostgreSQL: order, resumption, the end, the bounds."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import torch
from fastapi.testclient import TestClient

import sim.market
from server.app import create_app
from server.auctions import steps
from server.auctions.steps import run_step
from server.cli.launch import ServerProcess
from server.work.pool import WorkerContext
from tests.support.live import (
    PacedMarket,
    create_unstarted_auction,
    data,
    paced_auction,
    play_to_end,
    sse_events,
    submit_population,
)
from tests.support.server import ADMIN, ADMIN_TOKEN, make_settings, wait_for

MAX_STREAMS = 4
KEEPALIVE_S = 0.3
STREAM_TIMEOUT = httpx.Timeout(30.0)


@pytest.fixture(scope="module")
def server(database_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    env = {
        "SRD_EVENT_KEEPALIVE_S": str(KEEPALIVE_S),
        "SRD_EVENT_POLL_INTERVAL_S": "0.05",
        "SRD_MAX_EVENT_STREAMS": str(MAX_STREAMS),
        "SRD_PROGRESS_INTERVAL_S": "0.1",
    }
    data_dir = tmp_path_factory.mktemp("server")
    with ServerProcess(
        database_url=database_url, data_dir=data_dir, admin_token=ADMIN_TOKEN, extra_env=env
    ) as running:
        yield running


@pytest.fixture(scope="module")
def client(server: ServerProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=STREAM_TIMEOUT) as http:
        yield http


@pytest.fixture(scope="module")
def honest_ids(client: httpx.Client) -> list[int]:
    answers = submit_population(client)
    return [a["model_id"] for name, a in answers.items() if name.startswith("honest")]


def follow(client: httpx.Client, path: str, **headers: str) -> list[dict[str, str]]:
    """Every event of a stream until the server closes it (comments left out)."""
    with client.stream("GET", path, headers=headers) as response:
        assert response.status_code == 200, response.read()
        assert response.headers["content-type"].startswith("text/event-stream")
        return [e for e in sse_events(response) if "event" in e]


def purchases_by_round(auction: dict[str, Any]) -> dict[int, list[tuple[int, float]]]:
    """``GET /auctions/{id}``'s buyers, grouped by the round they bought in."""
    rounds: dict[int, list[tuple[int, float]]] = {}
    for buyer in auction["buyers"]:
        rounds.setdefault(buyer["iteration"], []).append((buyer["model_id"], buyer["price"]))
    return rounds


@pytest.mark.postgres_in_slow_run
def test_auction_stream_is_the_committed_history_then_the_end(
    client: httpx.Client, honest_ids: list[int]
) -> None:
    created = client.post("/auctions", json={"n_fish": 3, "seed": 0}, headers=ADMIN)
    auction_id = created.json()["auction_id"]
    events = follow(client, f"/auctions/{auction_id}/events")
    auction = client.get(f"/auctions/{auction_id}").json()
    assert auction["status"] == "finished"
    rounds, end = events[:-1], events[-1]
    assert [e["event"] for e in rounds] == ["iteration"] * len(auction["history"])
    assert [e["id"] for e in rounds] == [str(i) for i in range(len(auction["history"]))]
    bought = purchases_by_round(auction)
    for event, row in zip(rounds, auction["history"], strict=True):
        sent = data(event)
        assert {k: sent[k] for k in row} == row
        purchases = [(p["model_id"], p["price"]) for p in sent["purchases"]]
        assert purchases == bought.get(row["iteration"], [])
    assert [q["model_id"] for e in rounds for q in data(e)["quits"]] == auction["quitters"]
    names = {p["participant"] for e in rounds for p in data(e)["purchases"] + data(e)["quits"]}
    assert names and all(name.startswith("honest-") for name in names)
    assert end["event"] == "end" and "id" not in end
    assert data(end) == {
        "status": "finished",
        "iterations": len(auction["history"]),
        "price": auction["price"],
        "n_available": auction["n_available"],
        "n_initial": 3,
        "n_sold": len(auction["buyers"]),
        "stop_reason": auction["stop_reason"],
        "error": None,
        "finished_at": auction["finished_at"].replace("+00:00", "Z"),
    }


def test_events_arrive_while_it_runs_and_resume_skips_and_repeats_nothing(
    client: httpx.Client,
    server: ServerProcess,
    honest_ids: list[int],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    torch.set_num_threads(1)
    auction_id = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=1)
    first: list[dict[str, str]] = []
    with paced_auction(monkeypatch, server.database_url, server.data_dir, auction_id, pace_s=0.3):
        path = f"/auctions/{auction_id}/events"
        with client.stream("GET", path) as response:
            for event in sse_events(response):
                if event.get("event") == "iteration":
                    first.append(event)
                    state = client.get(f"/auctions/{auction_id}").json()
                    assert state["status"] == "running"  # it arrived while the auction ran
                    # committed before it was sent (a busy machine may commit the next one
                    # before this read, so only the lower bound is certain)
                    assert len(state["history"]) >= len(first)
                if len(first) == 2:
                    break  # the client goes away mid-auction
        resumed = follow(client, path, **{"Last-Event-ID": first[-1]["id"]})
        also = follow(client, f"{path}?after=0", **{"Last-Event-ID": "1"})  # the header wins
    auction = client.get(f"/auctions/{auction_id}").json()
    ids = [e["id"] for e in first + resumed if e["event"] == "iteration"]
    assert ids == [str(i) for i in range(len(auction["history"]))]  # nothing skipped or repeated
    assert len(auction["history"]) > 2 and resumed[-1]["event"] == "end"
    assert [data(e) for e in also] == [data(e) for e in resumed]
    from_query = follow(client, f"{path}?after={len(auction['history']) - 2}")
    assert [e["event"] for e in from_query] == ["iteration", "end"]


def test_a_long_step_takes_turns_and_plays_the_auction_it_would_have_played_at_once(
    client: httpx.Client,
    server: ServerProcess,
    honest_ids: list[int],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A step ends once it has played ``STEP_SLICE_S`` (after the iteration it committed), the
    auction still running and due, so a long auction takes turns with the others' steps on the
    workers instead of holding one to its end; the steps after it resume from the commits and
    play exactly the auction one step would have."""
    torch.set_num_threads(1)
    context = WorkerContext(
        database_url=server.database_url,
        data_dir=str(server.data_dir),
        progress_interval_s=0.1,
        torch_threads=1,
    )
    whole = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=1)
    assert play_to_end(context, whole) == 1  # quick: within one step
    sliced = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=1)
    monkeypatch.setattr(steps, "STEP_SLICE_S", 0.5)
    monkeypatch.setattr(PacedMarket, "pace_s", 0.3)
    monkeypatch.setattr(sim.market, "Market", PacedMarket)
    run_step(context, sliced)
    after_one = client.get(f"/auctions/{sliced}").json()
    assert after_one["status"] == "running" and 1 <= len(after_one["history"]) <= 3, after_one
    assert play_to_end(context, sliced) > 1
    played = [client.get(f"/auctions/{a}").json() for a in (whole, sliced)]

    def outcome(auction: dict[str, Any]) -> dict[str, Any]:
        rows = [{k: v for k, v in r.items() if not k.endswith("_at")} for r in auction["history"]]
        kept = ("status", "price", "n_available", "buyers", "quitters", "stop_reason")
        return {"history": rows, **{k: auction[k] for k in kept}}

    assert outcome(played[1]) == outcome(played[0])
    assert len(played[0]["history"]) > 2


def test_remote_fine_tuning_rounds_appear_between_the_iterations(
    client: httpx.Client, honest_ids: list[int]
) -> None:
    body = {
        "n_fish": 1,
        "seed": 1,
        "model_ids": honest_ids,
        "fine_tune_mode": "remote",
        "fine_tune_rounds": 2,
        "round_deadline_s": 0.5,  # nobody uploads: each round waits this long, then closes
    }
    auction_id = client.post("/auctions", json=body, headers=ADMIN).json()["auction_id"]
    path = f"/auctions/{auction_id}/events?rounds=true"  # the rounds are asked for
    events = follow(client, path)
    auction = client.get(f"/auctions/{auction_id}").json()
    ids = [e["id"] for e in events[:-1]]
    positions = [tuple(int(part) for part in i.split(".")) + (0,) * ("." not in i) for i in ids]
    assert positions == sorted(positions) and len(set(ids)) == len(ids)
    closed = [data(e) for e in events if e.get("event") == "round" and e["id"].endswith(".2")]
    assert closed == auction["fine_tuning"] and [r["round"] for r in closed] == [1, 2]
    assert all(a["outcome"] == "missing" for r in closed for a in r["answers"])
    opened = [e["id"] for e in events if e.get("event") == "round" and e["id"].endswith(".1")]
    assert opened  # seen while the round was open (each waits 0.5 s, the watcher reads often)
    assert ids.index("0.2") == ids.index("0") + 1 + ("0.1" in ids)  # right after iteration 0
    assert ids.index("1") == ids.index("0.2") + 1
    resumed = follow(client, path, **{"Last-Event-ID": "0.1"})
    assert [e.get("id") for e in resumed][:2] == ["0.2", "1"]
    last = len(auction["history"]) - 1  # an ended auction opens no round after its last
    for never_sent in (f"{last}.1", f"{last}.2"):
        ahead = client.get(path, headers={"Last-Event-ID": never_sent})
        assert ahead.status_code == 422, ahead.text
        [item] = ahead.json()["detail"]
        assert item["type"] == "ahead" and item["loc"] == ["header", "Last-Event-ID"]
        assert item["msg"].endswith(f"its iteration {last} has no fine-tuning round after it")
    # Not asked for, the stream is the contract's: one event per iteration, id = iteration.
    plain = follow(client, f"/auctions/{auction_id}/events")
    assert [e["event"] for e in plain] == ["iteration"] * len(auction["history"]) + ["end"]
    assert [e["id"] for e in plain[:-1]] == [str(i) for i in range(len(auction["history"]))]


def test_idle_streams_keep_alive_and_are_bounded_and_freed(
    client: httpx.Client, server: ServerProcess, honest_ids: list[int]
) -> None:
    auction_id = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=0)
    path = f"/auctions/{auction_id}/events"
    streams = [client.stream("GET", path) for _ in range(MAX_STREAMS)]
    opened = [stream.__enter__() for stream in streams]
    try:
        for response in opened:
            assert response.status_code == 200
        events = sse_events(opened[0])
        assert next(events)["comment"] == f"auction {auction_id}"
        assert next(events) == {"comment": "keep-alive"}  # pending: nothing to send yet
        refused = client.get(path, timeout=5)
        assert refused.status_code == 503
        assert refused.headers["Retry-After"] == "5"
        (item,) = refused.json()["detail"]
        assert item["type"] == "too_many_streams" and item["loc"] == ["server"]
        streams.pop().__exit__(None, None, None)  # a client disconnects: its slot comes back
        opened.pop()
        assert status_once_freed(client, path) == 200
    finally:
        for stream in streams:
            stream.__exit__(None, None, None)


def status_once_freed(client: httpx.Client, path: str, timeout_s: float = 5.0) -> int:
    """The status of a new stream, retried while the server is still releasing a slot."""
    deadline = time.monotonic() + timeout_s
    while True:
        with client.stream("GET", path) as response:
            if response.status_code != 503 or time.monotonic() > deadline:
                return response.status_code
        time.sleep(0.05)


@pytest.mark.postgres_in_slow_run
def test_job_stream_reports_progress_then_the_whole_job(client: httpx.Client) -> None:
    body = {"kind": "fish", "params": {"steps": 600, "seed": 0}}
    job_id = client.post("/jobs", json=body, headers=ADMIN).json()["job_id"]
    events = follow(client, f"/jobs/{job_id}/events")
    progress, end = events[:-1], events[-1]
    assert progress and all(e["event"] == "progress" for e in progress)
    ids = [int(e["id"]) for e in progress]
    assert ids == sorted(set(ids))  # each change once, in order
    fractions = [data(e)["progress"] for e in progress]
    assert fractions == sorted(fractions)
    assert {data(e)["status"] for e in progress} <= {"queued", "running"}
    job = client.get(f"/jobs/{job_id}").json()
    assert end["event"] == "end" and data(end)["status"] == "succeeded"
    assert data(end)["result"] == job["result"] and data(end)["artifacts"] == job["artifacts"]
    again = follow(client, f"/jobs/{job_id}/events", **{"Last-Event-ID": progress[-1]["id"]})
    assert [e["event"] for e in again] == ["end"]  # nothing it had already seen


def test_stream_errors_use_the_error_body(
    client: httpx.Client, server: ServerProcess, honest_ids: list[int]
) -> None:
    missing = client.get("/auctions/999999/events")
    assert missing.status_code == 404
    assert missing.json()["detail"][0]["loc"] == ["path", "auction_id"]
    assert client.get("/jobs/999999/events").status_code == 404
    auction_id = create_unstarted_auction(server.database_url, honest_ids, n_fish=1, seed=0)
    path = f"/auctions/{auction_id}/events"
    for bad_id in ("soon", "-1", "1.3", "1.2.1"):
        bad = client.get(path, headers={"Last-Event-ID": bad_id})
        assert bad.status_code == 422
        assert bad.json()["detail"][0]["loc"] == ["header", "Last-Event-ID"]
    for ahead, loc in (
        ({"Last-Event-ID": "3"}, ["header", "Last-Event-ID"]),
        ({}, ["query", "after"]),
    ):
        # an id the stream never sent: it would wait for events that never come, or skip some
        bad = client.get(path, headers=ahead, params={} if ahead else {"after": "0.1"})
        assert bad.status_code == 422
        [item] = bad.json()["detail"]
        assert item["loc"] == loc and item["type"] == "ahead"
        assert "which has sent no iteration so far" in item["msg"], item
    negative = client.get(f"{path}?after=-1")
    assert negative.status_code == 422
    assert negative.json()["detail"][0]["loc"] == ["query", "after"]
    for spelling in ("yes", "1", "on", "TRUE"):  # true or false, as every boolean of the API
        lax = client.get(path, params={"rounds": spelling})
        assert lax.status_code == 422, spelling
        (item,) = lax.json()["detail"]
        assert item["loc"] == ["query", "rounds"] and "true or false" in item["msg"], item
    job = client.post("/jobs", json={"kind": "fish", "params": {"steps": 10}}, headers=ADMIN)
    job_path = f"/jobs/{job.json()['job_id']}/events"
    for stream in (path, job_path):  # each problem said once
        bad = client.get(stream, headers={"Last-Event-ID": "abc"}, params={"after": "abc"})
        assert bad.status_code == 422
        assert sorted(i["loc"] for i in bad.json()["detail"]) == [
            ["header", "Last-Event-ID"],
            ["query", "after"],
        ]
    for dotted in ("3.1", "1.5"):  # a job's ids are whole numbers, and its pattern says so
        bad = client.get(job_path, headers={"Last-Event-ID": dotted})
        assert bad.status_code == 422
        (item,) = bad.json()["detail"]
        assert item["loc"] == ["header", "Last-Event-ID"] and "{1,18}$" in item["msg"]
        assert "\\.[12]" not in item["msg"], item


def test_a_client_leaving_a_full_stream_is_no_error(tmp_path: Path) -> None:
    """FastAPI's event streams close their output before they stop the task that fills it: a
    client that left a stream whose socket pushed back ended the request with an error
    (``ExceptionGroup`` of ``BrokenResourceError``, logged by uvicorn as "Exception in ASGI
    application" with a traceback, on every such leave). Driven as uvicorn drives the app
    (ASGI 2.3: the response listens for the disconnect), with a reader that stops reading."""
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path / "data")
    with TestClient(create_app(settings)) as http:
        submit_population(http)
        created = http.post("/auctions", json={"n_fish": 3, "seed": 0}, headers=ADMIN)
        auction_id = created.json()["auction_id"]
        wait_for(
            lambda: http.get(f"/auctions/{auction_id}").json(),
            lambda a: a["status"] == "finished",
            120,
        )

        async def leave_a_full_stream() -> str:
            sent: list[dict[str, Any]] = []

            async def send(message: dict[str, Any]) -> None:
                sent.append(message)
                if len(sent) > 2:  # the headers and one event, then the socket is full
                    await asyncio.Event().wait()

            asked = 0

            async def receive() -> dict[str, Any]:
                nonlocal asked
                asked += 1
                if asked == 1:
                    return {"type": "http.request", "body": b"", "more_body": False}
                await asyncio.sleep(0.3)
                return {"type": "http.disconnect"}

            scope = {
                "type": "http",
                "asgi": {"version": "3.0", "spec_version": "2.3"},
                "http_version": "1.1",
                "method": "GET",
                "scheme": "http",
                "path": f"/auctions/{auction_id}/events",
                "raw_path": f"/auctions/{auction_id}/events".encode(),
                "query_string": b"",
                "root_path": "",
                "headers": [(b"host", b"test")],
                "client": ("127.0.0.1", 5000),
                "server": ("127.0.0.1", 80),
            }
            try:
                await asyncio.wait_for(http.app(scope, receive, send), 10)
            except BaseException as exc:  # what the server would log
                return repr(exc)
            assert sent[0]["status"] == 200
            return "left"

        assert [http.portal.call(leave_a_full_stream) for _ in range(5)] == ["left"] * 5
