"""Faults in the middle of an auction, against a real ``srd serve``: an auction is state in the
database moved by steps, so a worker killed mid-step or mid-round costs nothing but time (the
auction finishes identical to an undisturbed twin), and an upload whose body reached the server
before its round's deadline counts as in time even if the server is killed before it could be
judged (a retry of the same body gets its verdict after the restart)."""

from __future__ import annotations

import contextlib
import functools
import os
import secrets
import signal
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from agents.manifest import parse_manifest
from agents.remote import RoundInfo, faithful_fine_tune
from server.cli.launch import ServerProcess
from server.store.db import Database
from server.store.tables import FineTuneAnswer, FineTuneRound
from tests.support.databases import BACKENDS, fresh_database
from tests.support.factories import honest
from tests.support.live import sse_events
from tests.support.processes import descendants, process_name, server_pair
from tests.support.remote import next_round
from tests.support.server import wait_for

TIMEOUT_S = 180
SAME = ("history", "buyers", "quitters", "stop_reason", "price", "n_available", "revenue")
"""What an auction and its twin must agree on."""


def spawned(server: ServerProcess) -> list[int]:
    """The server's worker processes (the screening process, auction and job workers), found
    by the names they give themselves (``srd-...``); not their fork server nor multiprocessing's
    resource tracker."""
    assert server.process is not None
    found = [
        pid
        for pid in descendants(server.process.pid)[1:]
        if (process_name(pid) or "").startswith("srd-")
    ]
    assert any(process_name(pid) == "srd-screening" for pid in found), "no screening process"
    return found


def signal_all(pids: list[int], signum: int) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signum)


def get(server: ServerProcess, auction_id: int) -> dict[str, Any]:
    return dict(httpx.get(f"{server.url}/auctions/{auction_id}", timeout=30).json())


def ended(server: ServerProcess, auction_id: int) -> dict[str, Any]:
    return wait_for(
        lambda: get(server, auction_id),
        lambda a: a["status"] not in ("pending", "running"),
        TIMEOUT_S,
    )


def _post_retrying(url: str, body: dict[str, Any]) -> dict[str, Any]:
    """POST, again after a 503 (a screener killed by the test is starting again)."""
    for _ in range(60):
        answer = httpx.post(url, json=body, timeout=60)
        if answer.status_code != 503:
            return dict(answer.json())
        time.sleep(1)
    raise AssertionError(f"{url}: still 503 after a minute")


Population = tuple[list[int], list[dict[str, Any]], list[str]]
"""Model ids, manifests and tokens of freshly submitted participants."""


def submit(server: ServerProcess, n: int, seed: int) -> Population:
    """``n`` honest participants whose weights depend on ``seed`` and their index only (a twin
    population has the same weights under other names)."""
    tag = secrets.token_hex(3)
    manifests = [honest(f"fault-{tag}-{i}", seed=seed + i) for i in range(n)]
    answers = [_post_retrying(server.url + "/submit", m) for m in manifests]
    assert all(a["accepted"] for a in answers), answers
    return [a["model_id"] for a in answers], manifests, [a["token"] for a in answers]


def create(server: ServerProcess, admin: dict[str, str], body: dict[str, Any]) -> int:
    created = httpx.post(server.url + "/auctions", json=body, headers=admin, timeout=30)
    assert created.status_code == 201, created.text
    return int(created.json()["auction_id"])


def kill_mid_step(server: ServerProcess, admin: dict[str, str], body: dict[str, Any]) -> int:
    """An auction whose step is killed (every spawned process of the server) while it plays:
    tried on fresh auctions until a kill lands while the auction is still running."""
    for _ in range(KILL_TRIES):
        ids, _, _ = submit(server, 32, seed=700)
        auction_id = create(server, admin, {**body, "model_ids": ids})
        deadline = time.monotonic() + TIMEOUT_S
        while get(server, auction_id)["iteration"] < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        workers = spawned(server)
        names = {process_name(pid) for pid in workers}
        signal_all(workers, signal.SIGKILL)
        if get(server, auction_id)["status"] == "running":
            assert "srd-auction-wor" in names, names  # the step's worker was among them
            return auction_id
        ended(server, auction_id)  # it finished before the kill: try another
    raise AssertionError(f"no kill landed mid-step in {KILL_TRIES} auctions")


KILL_TRIES = 5


def test_a_worker_killed_mid_step_resumes_and_matches_its_twin(tmp_path: Path) -> None:
    (server, _), admin = server_pair(f"sqlite:///{tmp_path / 'steps.db'}", tmp_path)
    with server:
        body = {"n_fish": 8, "fine_tune": True, "max_iterations": 40, "seed": 11}
        killed = kill_mid_step(server, admin, body)
        played = ended(server, killed)
        twin_ids, _, _ = submit(server, 32, seed=700)
        twin = ended(server, create(server, admin, {**body, "model_ids": twin_ids}))
    assert played["status"] == "finished" and played["error"] is None
    assert [r["iteration"] for r in played["history"]] == list(range(len(played["history"])))
    position = {m: i for i, m in enumerate(played["model_ids"])}
    twin_position = {m: i for i, m in enumerate(twin["model_ids"])}
    for key in ("history", "stop_reason", "price", "n_available", "revenue"):
        assert played[key] == twin[key], key
    assert [(position[b["model_id"]], b["price"]) for b in played["buyers"]] == [
        (twin_position[b["model_id"]], b["price"]) for b in twin["buyers"]
    ]
    assert [position[q] for q in played["quitters"]] == [twin_position[q] for q in twin["quitters"]]


@pytest.mark.slow  # a minute of kills: the single kill mid-step and mid-round run by default
def test_a_worker_killed_again_and_again_while_its_auction_moves_on_does_not_fail_it(
    tmp_path: Path,
) -> None:
    """Three deaths in a row fail an auction (a step that kills its worker every time), but
    deaths between which the auction committed iterations are an outside killer's (memory
    pressure, an operator): each only costs time, and the auction ends as its twin does."""
    (server, _), admin = server_pair(f"sqlite:///{tmp_path / 'kills.db'}", tmp_path)
    with server:
        # one fish among 24 keen buyers: the price climbs for dozens of iterations
        body = {"n_fish": 1, "fine_tune": True, "fine_tune_rounds": 64, "max_iterations": 200}
        body |= {"rows": 256, "seed": 6}
        ids, _, _ = submit(server, 24, seed=710)
        auction_id = create(server, admin, {**body, "model_ids": ids})
        kills, seen = 0, 0
        deadline = time.monotonic() + TIMEOUT_S
        while kills < 4 and time.monotonic() < deadline:
            state = get(server, auction_id)
            if state["status"] not in ("pending", "running"):
                break
            if state["iteration"] > seen:  # it moved on since the last kill: kill it again
                seen = state["iteration"]
                workers = [p for p in spawned(server) if process_name(p) == "srd-auction-wor"]
                # all stopped, then all killed: as one blow (a worker handed the auction as
                # another died would otherwise die a second time, before it began)
                signal_all(workers, signal.SIGSTOP)
                signal_all(workers, signal.SIGKILL)
                kills += bool(workers)
            time.sleep(0.02)
        assert kills == 4, f"after {kills} kills: {state['status']}, {state['error']}"
        played = ended(server, auction_id)
        twin_ids, _, _ = submit(server, 24, seed=710)
        twin = ended(server, create(server, admin, {**body, "model_ids": twin_ids}))
    assert played["status"] == "finished" and played["error"] is None, played["error"]
    for key in ("history", "stop_reason", "price", "n_available", "revenue"):
        assert played[key] == twin[key], key


def upload(
    server: ServerProcess,
    auction_id: int,
    state: dict[str, Any],
    model_id: int,
    manifests: dict[int, dict[str, Any]],
    tokens: dict[int, str],
    ids: list[int],
) -> httpx.Response:
    """The patron's faithful fine-tuning of the open round ``state``, uploaded (a 503 of a
    screener that is starting again is retried, as an agent would)."""
    tuned = faithful_fine_tune(
        parse_manifest(manifests[model_id]), RoundInfo.from_state(state, ids.index(model_id))
    )
    url = f"{server.url}/auctions/{auction_id}/rounds/{state['round']}/models/{model_id}"
    headers = {"Authorization": f"Bearer {tokens[model_id]}", "Content-Type": "application/json"}
    for _ in range(60):
        answer = httpx.put(url, content=tuned.model_dump_json(), headers=headers, timeout=60)
        if answer.status_code != 503:
            return answer
        time.sleep(1)
    return answer


def play_remote(
    server: ServerProcess,
    auction_id: int,
    population: Population,
    *,
    kill_in_round: int | None = None,
    close_in_rounds: tuple[int, ...] = (),
) -> dict[str, Any]:
    """Answer every round of a remote auction with every asked patron's faithful fine-tuning;
    with ``kill_in_round``, kill -9 every spawned process of the server while that round is
    open, before its answers; in each of ``close_in_rounds``, stop the auction workers before
    the round's last answer, check that its verdict closed the round while no step could run,
    and kill -9 them (the step handed to a stopped worker dies with it)."""
    ids, manifest_list, token_list = population
    manifests, tokens = (
        dict(zip(ids, manifest_list, strict=True)),
        dict(zip(ids, token_list, strict=True)),
    )
    after = 0
    while True:
        state = next_round(server, auction_id, after, TIMEOUT_S)
        if state["auction_status"] not in ("pending", "running"):
            return ended(server, auction_id)
        if state["round"] == kill_in_round:
            signal_all(spawned(server), signal.SIGKILL)
        stopped: list[int] = []
        for k, model_id in enumerate(state["asked"]):
            if state["round"] in close_in_rounds and k == len(state["asked"]) - 1:
                stopped = [p for p in spawned(server) if process_name(p) == "srd-auction-wor"]
                assert stopped, "no auction worker to stop"
                signal_all(stopped, signal.SIGSTOP)
                before = get(server, auction_id)
            answer = upload(server, auction_id, state, model_id, manifests, tokens, ids)
            assert answer.status_code == 200, answer.text
        if stopped:
            closed = get(server, auction_id)
            assert closed["fine_tuning"][-1]["round"] == state["round"]
            assert closed["fine_tuning"][-1]["status"] == "closed"
            assert closed["iteration"] == before["iteration"]  # no step has played on
            signal_all(stopped, signal.SIGKILL)
        after = state["round"]


@pytest.mark.parametrize(
    "fault",
    [{"kill_in_round": 1}, pytest.param({"close_in_rounds": (1, 2, 3)}, marks=pytest.mark.slow)],
    ids=["kill", "close"],
)
def test_workers_killed_mid_round_cost_nothing_but_time(
    tmp_path: Path, fault: dict[str, Any]
) -> None:
    """Every spawned process killed while round 1 is open (``kill_in_round``), or, in each of
    three rounds, the auction workers stopped before its last answer, whose verdict closes the
    round while no step can run, then killed, the step they were handed dying with them
    (``close_in_rounds``: three deaths of three steps, each resumed, are not three deaths in a
    row): the auction matches its undisturbed twin."""
    (server, _), admin = server_pair(f"sqlite:///{tmp_path / 'rounds.db'}", tmp_path)
    body = {
        "n_fish": 2,
        "fine_tune_mode": "remote",
        "fine_tune_rounds": 3,
        "round_deadline_s": 120,
        "max_iterations": 12,
        "seed": 5,
    }
    with server:
        population = submit(server, 6, seed=800)
        killed = create(server, admin, {**body, "model_ids": population[0]})
        played = play_remote(server, killed, population, **fault)
        twin_population = submit(server, 6, seed=800)
        twin = create(server, admin, {**body, "model_ids": twin_population[0]})
        undisturbed = play_remote(server, twin, twin_population)
    assert played["status"] == "finished" and played["error"] is None
    assert played["history"] == undisturbed["history"]
    assert len(played["fine_tuning"]) == 3
    for rounds in (played["fine_tuning"], undisturbed["fine_tuning"]):
        assert all(a["outcome"] == "accepted" for r in rounds for a in r["answers"])
    assert [len(r["answers"]) for r in played["fine_tuning"]] == [
        len(r["answers"]) for r in undisturbed["fine_tuning"]
    ]


def test_uploads_that_reached_the_server_in_time_count_after_a_kill_9(tmp_path: Path) -> None:
    """The screener and the workers are frozen (SIGSTOP), so every upload is stored on arrival
    but none is judged; the server is killed with all of them in flight and comes back after
    the round's deadline: each upload is judged, none is late, and a retry of the same body
    gets the same answer."""
    url = f"sqlite:///{tmp_path / 'inflight.db'}"
    (first, second), admin = server_pair(url, tmp_path)
    deadline_s = 12.0
    try:
        first.start()
        ids, manifest_list, token_list = submit(first, 5, seed=900)
        manifests = dict(zip(ids, manifest_list, strict=True))
        tokens = dict(zip(ids, token_list, strict=True))
        auction_id = create(
            first,
            admin,
            {
                "n_fish": 1,
                "model_ids": ids,
                "fine_tune_mode": "remote",
                "fine_tune_rounds": 1,
                "round_deadline_s": deadline_s,
                "seed": 2,
            },
        )
        state = next_round(first, auction_id, 0, TIMEOUT_S)
        asked = list(state["asked"])
        frozen = spawned(first)
        signal_all(frozen, signal.SIGSTOP)
        threads = [
            threading.Thread(
                target=lambda m=m: _swallow(
                    lambda: upload(first, auction_id, state, m, manifests, tokens, ids)
                ),
                daemon=True,
            )
            for m in asked
        ]
        for thread in threads:
            thread.start()
        database = Database(url)
        try:
            wait_for(lambda: {"stored": _stored(database, auction_id)},
                     lambda s: s["stored"] == ["pending"] * len(asked), 30)  # fmt: skip
        finally:
            database.close()
        first.kill()
        signal_all(frozen, signal.SIGKILL)
        signal_all(frozen, signal.SIGCONT)
        deadline = datetime.fromisoformat(state["deadline"].replace("Z", "+00:00"))
        time.sleep(max(0.0, (deadline - datetime.now(UTC)).total_seconds()) + 1.0)
        # the restart comes after the deadline

        second.start()
        answers = {m: upload(second, auction_id, state, m, manifests, tokens, ids) for m in asked}
        for model_id, answer in answers.items():
            assert answer.status_code == 200, answer.text
            assert answer.json()["accepted"] is True
            again = upload(second, auction_id, state, model_id, manifests, tokens, ids)
            assert again.status_code == 200 and again.content == answer.content
        auction = ended(second, auction_id)
        (only,) = auction["fine_tuning"]
        assert only["status"] == "closed"
        assert sorted(a["outcome"] for a in only["answers"]) == ["accepted"] * len(asked)
    finally:
        first.kill()
        second.stop()


@pytest.mark.slow  # two lives of a server; the kill -9 with uploads and the cancels run by default
def test_uploads_a_cancel_closed_the_round_on_are_judged_without_a_retry(
    tmp_path: Path,
) -> None:
    """Uploads stored in time, their requests cut off by a kill -9 before any verdict, in a
    round a cancel closes (before the kill, or after the restart): each is judged all the same,
    without a retry of its body, as its request would have been (they stayed pending)."""
    url = f"sqlite:///{tmp_path / 'cancelled.db'}"
    (first, second), admin = server_pair(url, tmp_path)
    try:
        first.start()
        manifests: dict[int, dict[str, Any]] = {}
        tokens: dict[int, str] = {}
        groups = []
        for _ in range(2):  # the same weights under other names: the same auction twice
            group, manifest_list, token_list = submit(first, 5, seed=900)
            manifests |= dict(zip(group, manifest_list, strict=True))
            tokens |= dict(zip(group, token_list, strict=True))
            groups.append(group)
        body = {"n_fish": 1, "fine_tune_mode": "remote", "seed": 2, "fine_tune_rounds": 1}
        auctions = [  # rounds open long enough for the restart
            create(first, admin, body | {"model_ids": group, "round_deadline_s": 300})
            for group in groups
        ]
        states = [next_round(first, auction_id, 0, TIMEOUT_S) for auction_id in auctions]
        frozen = spawned(first)
        signal_all(frozen, signal.SIGSTOP)  # stored on arrival, never judged
        for auction_id, state in zip(auctions, states, strict=True):
            for model_id in state["asked"]:
                group = groups[auctions.index(auction_id)]
                call = functools.partial(
                    upload, first, auction_id, state, model_id, manifests, tokens, group
                )
                threading.Thread(target=_swallow, args=(call,), daemon=True).start()
        database = Database(url)
        try:
            for auction_id, state in zip(auctions, states, strict=True):
                stored = ["pending"] * len(state["asked"])
                wait_for(lambda a=auction_id: {"stored": _stored(database, a)},
                         lambda s, n=stored: s["stored"] == n, 30)  # fmt: skip
        finally:
            database.close()
        before = httpx.delete(f"{first.url}/auctions/{auctions[0]}", headers=admin, timeout=30)
        assert before.status_code == 200, before.text  # its round closes, uploads pending
        first.kill()
        signal_all(frozen, signal.SIGKILL)
        signal_all(frozen, signal.SIGCONT)

        second.start()  # judges what the first left pending in closed rounds
        after = httpx.delete(f"{second.url}/auctions/{auctions[1]}", headers=admin, timeout=30)
        assert after.status_code == 200, after.text  # judged once the answer is sent
        for auction_id, state in zip(auctions, states, strict=True):
            auction = wait_for(
                lambda a=auction_id: get(second, a),
                lambda a: all(x["outcome"] != "pending" for x in a["fine_tuning"][0]["answers"]),
                TIMEOUT_S,
            )
            assert auction["status"] == "cancelled"
            (only,) = auction["fine_tuning"]
            outcomes = {a["model_id"]: a["outcome"] for a in only["answers"]}
            assert outcomes == dict.fromkeys(state["asked"], "accepted")
            assert all(a["uploaded_id"] is not None for a in only["answers"])
    finally:
        first.kill()
        second.stop()


@pytest.mark.postgres_in_slow_run
@pytest.mark.parametrize("backend", BACKENDS)
def test_a_round_its_last_verdict_closed_reads_closed_before_the_next_step(
    backend: str, tmp_path: Path
) -> None:
    """The step that plays on is held back (its workers stopped, as when they are all busy):
    the round the last upload's verdict closed reads closed at once, not when the next
    iteration is committed (the live reads did not see the close: it left the auction's
    ``updated_at`` as it was)."""
    for url in fresh_database(backend, tmp_path):
        _closed_before_the_next_step(url, tmp_path)


def _closed_before_the_next_step(url: str, tmp_path: Path) -> None:
    (server, _), admin = server_pair(url, tmp_path)
    with server:
        ids, manifest_list, token_list = submit(server, 5, seed=900)
        manifests = dict(zip(ids, manifest_list, strict=True))
        tokens = dict(zip(ids, token_list, strict=True))
        body = {"n_fish": 1, "model_ids": ids, "fine_tune_mode": "remote", "seed": 2}
        auction_id = create(server, admin, body | {"fine_tune_rounds": 1, "round_deadline_s": 120})
        state = next_round(server, auction_id, 0, TIMEOUT_S)
        current = f"{server.url}/auctions/{auction_id}/rounds/current"
        waiting = threading.Thread(  # a patron waiting for the next round: the round is watched
            target=_swallow,
            args=(lambda: httpx.get(current, params={"wait": 30, "after": 1}, timeout=60),),
            daemon=True,
        )
        waiting.start()
        seen: list[str] = []  # the event ids of the auction's stream, its rounds asked for

        def follow_rounds() -> None:
            events = f"{server.url}/auctions/{auction_id}/events"
            with httpx.stream("GET", events, params={"rounds": "true"}, timeout=60) as stream:
                seen.extend(event.get("id", "") for event in sse_events(stream))

        threading.Thread(target=_swallow, args=(follow_rounds,), daemon=True).start()
        time.sleep(0.5)
        steps = [p for p in spawned(server) if process_name(p) != "srd-screening"]
        signal_all(steps, signal.SIGSTOP)
        played = get(server, auction_id)["iteration"]
        try:
            for model_id in state["asked"]:
                answer = upload(server, auction_id, state, model_id, manifests, tokens, ids)
                assert answer.status_code == 200, answer.text
            wait_for(lambda: httpx.get(current, timeout=30).json(),
                     lambda c: c["status"] == "closed", 10)  # fmt: skip
            closed = f"{state['iteration']}.2"  # the event of the round's close
            wait_for(lambda: {"seen": list(seen)}, lambda s: closed in s["seen"], 10)
            assert get(server, auction_id)["iteration"] == played  # no step meanwhile
        finally:
            signal_all(steps, signal.SIGCONT)
        assert ended(server, auction_id)["status"] == "finished"


def _swallow(call: Any) -> None:
    """An upload cut off by the kill (its connection drops): nothing to report."""
    with contextlib.suppress(httpx.HTTPError):
        call()


def _stored(database: Database, auction_id: int) -> list[str]:
    with database.session(write=False) as session:
        return sorted(
            session.scalars(
                select(FineTuneAnswer.outcome)
                .join(FineTuneRound, FineTuneRound.id == FineTuneAnswer.round_id)
                .where(FineTuneRound.auction_id == auction_id)
            )
        )


@pytest.mark.slow  # 19 s; the default run keeps the kill -9 faults
def test_an_upload_waiting_for_a_hung_screener_hears_the_verdict_the_step_recorded(
    tmp_path: Path,
) -> None:
    """The screening process hangs (SIGSTOP) while an upload waits for its verdict: at the
    round's deadline the step that closes the round judges the pending upload itself, and the
    waiting request answers with that verdict within seconds of the deadline, instead of a 503
    when the screener's wait gives up (120 s), rounds later."""
    (server, _), admin = server_pair(f"sqlite:///{tmp_path / 'hung.db'}", tmp_path)
    deadline_s = 4.0
    with server:
        ids, manifest_list, token_list = submit(server, 3, seed=950)
        manifests = dict(zip(ids, manifest_list, strict=True))
        tokens = dict(zip(ids, token_list, strict=True))
        body = {"n_fish": 1, "model_ids": ids, "fine_tune_mode": "remote", "seed": 3}
        auction_id = create(
            server, admin, body | {"fine_tune_rounds": 1, "round_deadline_s": deadline_s}
        )
        state = next_round(server, auction_id, 0, TIMEOUT_S)
        screening = [p for p in spawned(server) if process_name(p) == "srd-screening"]
        signal_all(screening, signal.SIGSTOP)
        try:
            deadline = datetime.fromisoformat(state["deadline"].replace("Z", "+00:00"))
            answer = upload(server, auction_id, state, state["asked"][0], manifests, tokens, ids)
            late_by_s = (datetime.now(UTC) - deadline).total_seconds()
        finally:
            signal_all(screening, signal.SIGCONT)
        assert answer.status_code == 200, answer.text
        assert answer.json()["accepted"] is True and answer.json()["outcome"] == "accepted"
        assert late_by_s < 10, late_by_s  # the step's verdict, not the screener's give-up
        auction = ended(server, auction_id)
    (only,) = auction["fine_tuning"]
    outcomes = {a["model_id"]: a["outcome"] for a in only["answers"]}
    assert outcomes[state["asked"][0]] == "accepted"
