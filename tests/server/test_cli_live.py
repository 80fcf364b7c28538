"""``srd watch AUCTION_ID``: against a real ``srd serve`` (the iterations printed, the final
state, buyers and quitters named by participant and version), and against a stand-in server
whose stream drops (opened again, resuming after the last event)."""

from __future__ import annotations

import json
import os
import pty
import re
import signal
import socket
import stat
import subprocess
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler
from pathlib import Path
from typing import Any, ClassVar

import httpx
import pytest
from click.testing import CliRunner

from server.cli import cli
from server.cli.launch import ServerProcess, settings_environment, srd_command
from tests.support.fake_http import serving
from tests.support.live import submit_population
from tests.support.server import ADMIN, ADMIN_TOKEN, QUOTAS_OFF, module_server, wait_for

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    yield from module_server(tmp_path_factory, "watch")


@pytest.fixture(scope="module")
def client(server: ServerProcess) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=30) as http:
        submit_population(http)
        yield http


def watch(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*srd_command(), "watch", *args], capture_output=True, text=True, timeout=300, cwd=ROOT
    )


def start_auction(client: httpx.Client, seed: int) -> int:
    created = client.post("/auctions", json={"n_fish": 3, "seed": seed}, headers=ADMIN)
    assert created.status_code == 201, created.text
    return int(created.json()["auction_id"])


def test_watch_prints_each_iteration_and_exits_0_when_the_auction_finishes(
    server: ServerProcess, client: httpx.Client
) -> None:
    auction_id = start_auction(client, seed=0)
    done = watch(str(auction_id), "--server", server.url)
    assert done.returncode == 0, done.stderr
    auction = client.get(f"/auctions/{auction_id}").json()
    assert auction["status"] == "finished"
    lines = done.stdout.splitlines()
    rows = [line for line in lines if line.startswith("iteration ")]
    assert len(rows) == len(auction["history"]) >= 1
    for line, row in zip(rows, auction["history"], strict=True):
        votes = row["votes"]
        assert line.startswith(
            f"iteration {row['iteration']}: price {row['price']:.3f}, "
            f"fish {row['n_available']} -> {row['n_available_after']}, "
            f"votes buy {votes['buy']} hold {votes['hold']} quit {votes['quit']}"
        )
    for buyer in auction["buyers"]:
        bought = f"{buyer['participant']} v{buyer['version']} at {buyer['price']:.3f}"
        assert bought in rows[buyer["iteration"]]
    revenue = sum(b["price"] for b in auction["buyers"])
    assert lines[-1] == (
        f"auction {auction_id} finished ({auction['stop_reason']}) after "
        f"{len(auction['history'])} iterations: {len(auction['buyers'])} of 3 fish sold, "
        f"revenue {revenue:.3f}, price asked last {auction['history'][-1]['price']:.3f}"
    )


def test_watch_json_is_the_final_state_with_buyers_and_quitters_named(
    server: ServerProcess, client: httpx.Client
) -> None:
    auction_id = start_auction(client, seed=1)
    done = watch(str(auction_id), "--server", server.url, "--json")
    assert done.returncode == 0, done.stderr
    (line,) = done.stdout.splitlines()
    final = json.loads(line)
    assert final == client.get(f"/auctions/{auction_id}").json()
    assert final["status"] == "finished" and final["buyers"]
    for buyer in final["buyers"]:
        model = client.get(f"/models/{buyer['model_id']}").json()
        assert (buyer["participant"], buyer["version"]) == (model["participant"], model["version"])
    assert final["quitters"]  # some of the population's honest patrons quit
    assert [q["model_id"] for q in final["quitter_details"]] == final["quitters"]
    for quitter in final["quitter_details"]:
        model = client.get(f"/models/{quitter['model_id']}").json()
        assert (quitter["participant"], quitter["version"]) == (model["participant"], 1)
        votes = final["history"][quitter["iteration"]]["votes"]
        assert votes["quit"] >= 1


def test_an_enrolling_auction_nobody_joined_fails_and_the_server_logs_why(
    server: ServerProcess, client: httpx.Client
) -> None:
    created = client.post("/auctions", json={"n_fish": 1, "enrollment_s": 1}, headers=ADMIN)
    auction_id = created.json()["auction_id"]
    done = watch(str(auction_id), "--server", server.url)
    assert done.returncode == 1, done.stderr
    final = client.get(f"/auctions/{auction_id}").json()
    assert final["status"] == "failed"
    assert final["error"] == "nobody joined before its enrollment ended"
    # the worker logs every auction's outcome: finished, cancelled or failed
    logged = f"auction {auction_id} failed: nobody joined before its enrollment ended"
    assert logged in server.log_path.read_text()


def test_watch_of_an_unknown_auction_exits_3_naming_it(server: ServerProcess) -> None:
    done = watch("999999", "--server", server.url)
    assert done.returncode == 3
    assert f"auction 999999 not found on {server.url}" in done.stderr
    assert done.stdout == ""


def test_on_a_terminal_watch_draws_a_live_table(server: ServerProcess, client: httpx.Client):
    auction_id = start_auction(client, seed=2)
    wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] == "finished",
        120,
    )
    main, child = pty.openpty()
    process = subprocess.Popen(
        [*srd_command(), "watch", str(auction_id), "--server", server.url],
        stdout=child,
        stderr=subprocess.PIPE,
        cwd=ROOT,
        env={**os.environ, "COLUMNS": "160", "TERM": "xterm"},
    )
    os.close(child)
    screen = b""
    while True:
        try:
            chunk = os.read(main, 65536)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        screen += chunk
    os.close(main)
    assert process.wait(timeout=120) == 0
    text = screen.decode()
    for header in ("Iteration", "Price", "Fish left", "Buy", "Hold", "Quit", "Bought"):
        assert header in text
    assert f"auction {auction_id} finished" in text


# --- a stand-in server whose stream drops -------------------------------------------------------


def iteration(i: int) -> dict[str, Any]:
    return {
        "iteration": i,
        "price": 5.0 + i / 100,
        "n_available": 2,
        "n_available_after": 2,
        "next_price": 5.01 + i / 100,
        "votes": {"buy": 0, "hold": 3, "quit": 0},
        "purchases": [],
        "quits": [],
    }


END = {"status": "finished", "iterations": 3, "price": 5.03, "n_available": 2, "n_initial": 2}


class DroppingStream(BaseHTTPRequestHandler):
    """Sends ``plan[k]`` on the k-th connection (its events, an HTTP status with a JSON
    error, or keep-alives for a float of seconds), then closes it; records each
    Last-Event-ID."""

    plan: ClassVar[list[list[tuple[str, str | None, dict[str, Any]]] | int | float]] = []
    seen: ClassVar[list[str | None]] = []

    def do_GET(self) -> None:
        self.seen.append(self.headers.get("Last-Event-ID"))
        events = self.plan[min(len(self.seen), len(self.plan)) - 1]
        if isinstance(events, float):  # a quiet auction's stream: keep-alives only
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.end_headers()
            until = time.monotonic() + events
            while time.monotonic() < until:
                self.wfile.write(b": keep-alive\n\n")
                self.wfile.flush()
                time.sleep(0.25)
            return
        if isinstance(events, int):
            body = b'{"detail": [{"msg": "the database is unavailable"}]}'
            self.send_response(events)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)
            return
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.end_headers()
        self.wfile.write(b": auction 7\nretry: 2000\n\n")
        for name, event_id, data in events:
            block = f"event: {name}\ndata: {json.dumps(data)}\n"
            block += f"id: {event_id}\n\n" if event_id is not None else "\n"
            self.wfile.write(block.encode())
        self.wfile.flush()

    def log_message(self, format: str, *args: Any) -> None:  # quiet
        pass


@pytest.fixture
def dropping() -> Iterator[tuple[str, type[DroppingStream]]]:
    handler = type("Handler", (DroppingStream,), {"plan": [], "seen": []})
    with serving(handler) as url:
        yield url, handler


def test_a_dropped_stream_is_resumed_after_the_last_event(dropping) -> None:
    url, handler = dropping
    handler.plan = [
        [("iteration", "0", iteration(0)), ("iteration", "1", iteration(1))],
        [("iteration", "2", iteration(2)), ("end", None, END)],
    ]
    result = CliRunner().invoke(cli, ["watch", "7", "--server", url])
    assert result.exit_code == 0, result.output
    assert handler.seen == [None, "1"]
    rows = [line for line in result.stdout.splitlines() if line.startswith("iteration")]
    assert [row.split(":")[0] for row in rows] == ["iteration 0", "iteration 1", "iteration 2"]
    assert result.stdout.splitlines()[-1].startswith("auction 7 finished after 3 iterations")


def test_a_stream_kept_away_by_a_restarting_server_is_resumed(dropping) -> None:
    """A server restarting (the stream closed, then 503s while it is not ready) is waited
    out: the stream resumes after its last event, each wait said on stderr."""
    url, handler = dropping
    handler.plan = [
        [("iteration", "0", iteration(0))],
        503,
        503,
        [("iteration", "1", iteration(1)), ("end", None, END)],
    ]
    result = CliRunner().invoke(cli, ["watch", "7", "--server", url])
    assert result.exit_code == 0, result.output
    assert handler.seen == [None, "0", "0", "0"]
    told = [line for line in result.stderr.splitlines() if "dropped" in line]
    assert told[0].endswith("opening it again now")
    assert "HTTP 503" in told[1] and told[1].endswith("in 1 s")
    assert told[2].endswith("in 2 s")
    rows = [line for line in result.stdout.splitlines() if line.startswith("iteration")]
    assert [row.split(":")[0] for row in rows] == ["iteration 0", "iteration 1"]


def test_a_stream_had_again_then_dropped_again_is_waited_for_anew(dropping) -> None:
    """A stream opened again and held (a quiet auction sends keep-alives only) was had: its
    next drop starts a new wait, however long the quiet lasted."""
    url, handler = dropping
    handler.plan = [
        [("iteration", "0", iteration(0))],
        [],  # closed at once: the same drop
        2.5,  # held open, quiet, longer than --reconnect-s
        [("iteration", "1", iteration(1)), ("end", None, END)],
    ]
    result = CliRunner().invoke(cli, ["watch", "7", "--server", url, "--reconnect-s", "2"])
    assert result.exit_code == 0, result.output
    assert handler.seen == [None, "0", "0", "0"]


def test_a_stream_gone_longer_than_reconnect_s_exits_3(dropping) -> None:
    url, handler = dropping
    handler.plan = [[("iteration", "0", iteration(0))], []]  # then closed without an event
    started = time.monotonic()
    result = CliRunner().invoke(cli, ["watch", "7", "--server", url, "--reconnect-s", "1.5"])
    assert result.exit_code == 3
    assert 1.5 <= time.monotonic() - started < 10
    assert handler.seen[:2] == [None, "0"] and set(handler.seen[1:]) == {"0"}
    assert len(handler.seen) >= 3  # at once, then after 1 s, then at the window's end
    assert "the event stream dropped and could not be had again for 1.5 s" in result.stderr


def test_a_server_that_never_answers_is_named_not_a_dropped_stream() -> None:
    with socket.socket() as unused:  # a port nobody listens on
        unused.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{unused.getsockname()[1]}"
    result = CliRunner().invoke(cli, ["watch", "7", "--server", url])
    assert result.exit_code == 3
    assert f"the server at {url} did not answer" in result.stderr
    assert "dropped" not in result.stderr


def test_a_cancelled_auction_ends_the_watch_with_exit_1(dropping) -> None:
    url, handler = dropping
    cancelled = {**END, "status": "cancelled", "iterations": 1, "stop_reason": "cancelled"}
    closed = {"round": 1, "iteration": 0, "status": "closed", "answers": []}
    handler.plan = [
        [("iteration", "0", iteration(0)), ("round", "0.1", closed), ("end", None, cancelled)]
    ]
    result = CliRunner().invoke(cli, ["watch", "7", "--server", url])
    assert result.exit_code == 1
    lines = result.stdout.splitlines()
    assert "fine-tuning round 1 (after iteration 0): closed; no answers" in lines
    assert lines[-1].startswith("auction 7 cancelled after 1 iteration:")


# --- srd agents: the summary table ---------------------------------------------------------------


def cells(line: str) -> list[str]:
    """The cells of one line of a rich table (header lines have their own bars)."""
    return [cell.strip() for cell in re.split("[│┃]", line.strip().strip("│┃"))]


def test_agents_prints_a_row_per_agent_then_the_totals(
    server: ServerProcess, client: httpx.Client, tmp_path: Path
) -> None:
    options = ["--honest", "2", "--saboteurs", "1", "--rounds", "1", "--deadline", "20"]
    tokens = tmp_path / "tokens.json"
    done = subprocess.run(
        [*srd_command(), "agents", "--server", server.url, "--name-prefix", "table", *options,
         "--admin-token", ADMIN_TOKEN, "--tokens", str(tokens)],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE(tokens.stat().st_mode) == 0o600  # the tokens, for its owner alone
    saved = json.loads(tokens.read_text())
    assert [row["participant"] for row in saved] == [
        "table-honest-000", "table-honest-001", "table-saboteur-002"
    ]  # fmt: skip
    assert all(row["token"].startswith("srdp_") for row in saved)
    lines = done.stdout.splitlines()
    header = next(cells(line) for line in lines if "Participant" in line)
    assert header == [
        "Participant", "Model", "Submitted", "Uploads accepted", "Refused", "Held", "Late",
        "Missing", "Final version", "In the auction", "Bytes up", "Bytes down",
    ]  # fmt: skip
    rows = {c[0]: c for c in map(cells, lines) if c[0].startswith("table-")}
    assert sorted(rows) == ["table-honest-000", "table-honest-001", "table-saboteur-002"]
    auction_id = int(next(line for line in lines if "Auction" in line).split()[1].rstrip(":"))
    auction = client.get(f"/auctions/{auction_id}").json()
    answers = {a["model_id"]: a for r in auction["fine_tuning"] for a in r["answers"]}
    assert {str(row["model_id"]) for row in saved} == {row[1] for row in rows.values()}
    for row in rows.values():
        model_id = int(row[1])
        assert row[2] == "accepted"  # every agent's first model looks honest
        answer = answers.get(model_id)
        outcome = answer["outcome"] if answer else None
        kinds = ("accepted", "refused", "held", "late", "missing")
        assert row[3:8] == [str(int(outcome == kind)) for kind in kinds]
        assert row[8] == str(answer["version"] if answer else 1)
        bought = {b["model_id"]: b["price"] for b in auction["buyers"]}
        if model_id in bought:
            assert row[9] == f"bought at {bought[model_id]:.3f}"
        else:
            assert row[9] == ("quit" if model_id in auction["quitters"] else "stayed")
        assert int(row[10].replace(",", "")) > 0 and int(row[11].replace(",", "")) > 0
    if answers.get(int(rows["table-saboteur-002"][1])):
        assert rows["table-saboteur-002"][4] == "1"  # its always-hold upload is refused
    totals = next(cells(line) for line in lines if "3 agents" in line)
    assert totals[2] == "3 accepted"
    up = sum(int(row[10].replace(",", "")) for row in rows.values())
    assert int(totals[10].replace(",", "")) == up


def test_agents_whose_model_the_screener_refuses_stay_out_of_the_auction_they_create(
    server: ServerProcess, client: httpx.Client
) -> None:
    """Seed 21's twelfth honest draw is refused at the door (market impact): the auction is
    created among the accepted models, the refused agent is reported and does not play."""
    done = subprocess.run(
        [*srd_command(), "agents", "--server", server.url, "--name-prefix", "door",
         "--honest", "12", "--saboteurs", "0", "--seed", "21", "--rounds", "1",
         "--deadline", "20", "--admin-token", ADMIN_TOKEN, "--json"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    refused = [a for a in report["per_agent"] if a["submitted"] != "accepted"]
    assert [a["participant"] for a in refused] == ["door-honest-011"], report["per_agent"]
    (auction_id,) = report["auctions"]
    auction = client.get(f"/auctions/{auction_id}").json()
    assert auction["status"] == "finished"
    assert refused[0]["model_id"] not in auction["model_ids"]
    assert len(auction["model_ids"]) == 11 and report["admitted"] == 11


def test_agents_refuse_an_auction_that_takes_no_patrons_and_register_nothing(
    server: ServerProcess, client: httpx.Client
) -> None:
    """An auction created without enrollment_s has its patrons fixed: agents cannot join it,
    and are told so before they register anything."""
    existing = start_auction(client, seed=11)
    for auction_id, words in ((existing, "takes no patrons"), (999999, "does not exist")):
        done = subprocess.run(
            [*srd_command(), "agents", "--server", server.url, "--name-prefix", "late",
             "--honest", "1", "--auction", str(auction_id), "--json"],
            capture_output=True, text=True, timeout=120, cwd=ROOT,
        )  # fmt: skip
        assert done.returncode == 1, done.stderr
        assert f"auction {auction_id}" in done.stderr and words in done.stderr
        assert words in json.loads(done.stdout)["error"]  # --json: the failure, as one object
    assert client.get("/participants/late-honest-000").status_code == 404


def test_agents_stopped_midway_say_what_they_registered(
    server: ServerProcess, client: httpx.Client
) -> None:
    """Ctrl-C while the agents wait for their auction to start: exit 130, and what they made
    is not lost from sight: the models they registered and their auction, on stderr and in
    the --json object (their tokens are not printed: --tokens keeps them)."""
    created = client.post(
        "/auctions",
        json={"rarity": 0.5, "fine_tune_mode": "remote", "enrollment_s": 120, "seed": 4},
        headers=ADMIN,
    )
    assert created.status_code == 201, created.text
    auction_id = created.json()["auction_id"]
    process = subprocess.Popen(
        [*srd_command(), "agents", "--server", server.url, "--name-prefix", "stopped",
         "--honest", "2", "--auction", str(auction_id), "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    try:
        names = ["stopped-honest-000", "stopped-honest-001"]
        wait_for(
            lambda: {"found": [client.get(f"/participants/{n}").status_code for n in names]},
            lambda state: state["found"] == [200, 200],
            timeout_s=60,
        )
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        process.kill()
        process.wait()
        client.delete(f"/auctions/{auction_id}", headers=ADMIN)
    assert process.returncode == 130, stderr
    report = json.loads(stdout)
    assert report["error"] == "aborted" and report["auctions"] == [auction_id], report
    # the finished run's shape, as far as it got, and who registered
    assert report["agents"] == 2 and len(report["model_ids"]) == 2, report
    assert sorted(a["participant"] for a in report["registered"]) == names
    assert report["uploads"] == {"accepted": 0, "refused": 0, "late": 0, "held": 0}
    assert report["bytes_up"] > 0 and report["bytes_down"] > 0
    assert "token" not in stdout
    assert f"stopped: 2 models registered in auction {auction_id}" in stderr
    assert "their tokens are lost (--tokens keeps them" in stderr and "Aborted!" in stderr


@pytest.mark.slow  # the default run keeps its neighbours (docs/development.md)
def test_agents_join_an_enrolling_auction_and_play_it(
    server: ServerProcess, client: httpx.Client
) -> None:
    """srd agents --auction ID: the agents register, their accepted models join the auction
    while it enrolls, and they answer its rounds to its end."""
    created = client.post(
        "/auctions",
        json={
            "rarity": 0.5,
            "fine_tune_mode": "remote",
            "fine_tune_rounds": 1,
            "round_deadline_s": 20,
            "enrollment_s": 12,
            "seed": 3,
        },
        headers=ADMIN,
    )
    assert created.status_code == 201, created.text
    auction_id = created.json()["auction_id"]
    done = subprocess.run(
        [*srd_command(), "agents", "--server", server.url, "--name-prefix", "joiner",
         "--honest", "2", "--saboteurs", "1", "--auction", str(auction_id), "--json"],
        capture_output=True, text=True, timeout=180, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["auctions"] == [auction_id] and report["agents"] == 3
    auction = client.get(f"/auctions/{auction_id}").json()
    assert auction["status"] == "finished", auction["error"]
    assert sorted(auction["participants"]) == [
        "joiner-honest-000",
        "joiner-honest-001",
        "joiner-saboteur-002",
    ]
    assert auction["n_initial"] == 1  # int(0.5 × 3), counted when the enrollment ended
    assert report["uploads"]["accepted"] + report["uploads"]["refused"] >= 1


def test_agents_in_an_auction_cancelled_before_it_starts_say_they_were_stopped(
    server: ServerProcess, client: httpx.Client
) -> None:
    """Patrons still in when their auction is cancelled are ``stopped``, as
    ``GET /participants/{name}`` says (they were reported as having stayed to its end)."""
    created = client.post(
        "/auctions",
        json={"n_fish": 1, "fine_tune_mode": "remote", "enrollment_s": 60, "seed": 5},
        headers=ADMIN,
    )
    assert created.status_code == 201, created.text
    auction_id = created.json()["auction_id"]
    agents = subprocess.Popen(
        [*srd_command(), "agents", "--server", server.url, "--name-prefix", "halted",
         "--honest", "2", "--auction", str(auction_id), "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    try:
        wait_for(
            lambda: client.get(f"/auctions/{auction_id}").json(),
            lambda a: len(a["participants"]) == 2 or agents.poll() is not None,
            120,
        )
        assert client.delete(f"/auctions/{auction_id}", headers=ADMIN).status_code == 200
        out, err = agents.communicate(timeout=120)
    finally:
        agents.kill()
    assert agents.returncode == 0, err
    report = json.loads(out)
    assert [a["result"] for a in report["per_agent"]] == ["stopped", "stopped"], report
    name = report["per_agent"][0]["participant"]
    (entry,) = client.get(f"/participants/{name}").json()["auctions"]
    assert entry["outcome"] == "stopped"


def test_agents_check_the_operator_token_and_the_tokens_file_before_registering(
    server: ServerProcess, client: httpx.Client, tmp_path: Path
) -> None:
    """A wrong operator token, or a tokens file that cannot be written, is said before any
    participant is registered: nothing is left behind whose token nobody has."""
    base = [*srd_command(), "agents", "--server", server.url, "--honest", "2", "--json"]
    done = subprocess.run(
        [*base, "--name-prefix", "wrongtok", "--admin-token", "not-the-operator-token"],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert "not the operator token" in json.loads(done.stdout)["error"]
    assert client.get("/participants/wrongtok-honest-000").status_code == 404
    done = subprocess.run(
        [*base, "--name-prefix", "tokdir", "--admin-token", ADMIN_TOKEN,
         "--tokens", str(tmp_path / "no-such-folder" / "tokens.json")],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    failure = json.loads(done.stdout)
    assert [e["option"] for e in failure["errors"]] == ["--tokens"]
    assert "no such folder" in failure["error"] and "Traceback" not in done.stderr
    assert client.get("/participants/tokdir-honest-000").status_code == 404


class NotThisService(BaseHTTPRequestHandler):
    """Answers every request 200 with a JSON list: a server, but not an auction house."""

    def do_GET(self) -> None:
        body = b"[1, 2, 3]"
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_POST(self) -> None:
        self.do_GET()

    def log_message(self, *args: Any) -> None:
        pass


def test_agents_against_a_server_that_is_not_an_auction_house_exit_1_saying_so() -> None:
    with serving(NotThisService) as url:
        for extra in ([], ["--auction", "3"]):
            done = subprocess.run(
                [*srd_command(), "agents", "--server", url, "--honest", "1", "--give-up", "2",
                 "--wait", "1", "--json", *extra],
                capture_output=True, text=True, timeout=120, cwd=ROOT,
            )  # fmt: skip
            assert done.returncode == 1, done.stderr
            assert "Traceback" not in done.stderr
            assert "is it an srd server?" in json.loads(done.stdout)["error"]


@pytest.mark.slow  # a server of its own; the agents' token checks run by default
def test_agents_on_this_machine_use_the_token_file_its_srd_serve_wrote(tmp_path: Path) -> None:
    """With no --auction and no operator token, srd agents against a server on a loopback
    address takes the token ``srd serve`` generated in its data folder (SRD_DATA_DIR, or
    ./data), creates the auction and plays it; with no such file it says at once that it
    waits for an auction (it waited silently for --wait, 600 s by default)."""
    environment = {
        k: v for k, v in os.environ.items() if k not in ("SRD_ADMIN_TOKEN", "SRD_DATA_DIR")
    }
    with ServerProcess(
        database_url=f"sqlite:///{tmp_path / 'srd.db'}",
        data_dir=tmp_path / "data",
        extra_env=settings_environment(QUOTAS_OFF),
        cwd=tmp_path,
    ) as local:
        base = [*srd_command(), "agents", "--server", local.url, "--honest", "2", "--json"]
        done = subprocess.run(
            [*base, "--saboteurs", "1", "--rounds", "1", "--deadline", "20"],
            capture_output=True, text=True, timeout=300, cwd=tmp_path, env=environment,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        assert "operator token: data/admin_token" in done.stderr
        report = json.loads(done.stdout)
        assert len(report["auctions"]) == 1 and report["agents"] == 3
        elsewhere = tmp_path / "elsewhere"
        elsewhere.mkdir()
        waited = subprocess.run(
            [*base, "--name-prefix", "waiter", "--wait", "1"],
            capture_output=True, text=True, timeout=120, cwd=elsewhere, env=environment,
        )  # fmt: skip
        assert waited.returncode == 1
        said = " ".join(waited.stderr.split())  # one line, however the terminal wraps
        looked = elsewhere.resolve() / "data" / "admin_token"
        assert f"no --auction and no operator token (none in {looked}, where srd" in said
        assert "SRD_DATA_DIR names the server's" in said
        assert "wait up to 1 s (--wait)" in said and "--tokens keeps their tokens" in said
        assert "no auction contains model" in json.loads(waited.stdout)["error"]
        # Options it refuses are said before any word of waiting.
        refused = subprocess.run(
            [*base, "--honest", "0"], capture_output=True, text=True, timeout=120, cwd=elsewhere,
            env=environment,
        )  # fmt: skip
        assert refused.returncode == 2 and "--honest" in refused.stderr
        assert "wait up to" not in refused.stderr
