"""Bad input to ``srd watch``, ``srd screen``, ``srd healthcheck``, ``srd serve`` and the
experiment commands (a server that is not an srd server, ids, URLs, NaN, settings, oversized
files, a host, a Ray cluster, list options), and Ctrl-C: a clear error naming what is at fault
and the command's documented exit code, never a traceback."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
from click.testing import CliRunner, Result

from agents.negotiator import honest_manifest
from server.api.schemas import MAX_ROW_ID
from server.cli import cli
from server.cli.launch import ServerProcess, srd_command
from tests.support.fake_http import serving
from tests.support.server import ADMIN_TOKEN

ROOT = Path(__file__).resolve().parents[2]
HOST = "127.0.0.1"
NOT_SRD = "answered something that is not an srd auction"
INTERRUPTED = 130
TERMINATED = 143
ITERATION = {
    "iteration": 0,
    "price": 5.0,
    "n_available": 2,
    "n_available_after": 2,
    "next_price": 5.01,
    "votes": {"buy": 0, "hold": 3, "quit": 0},
    "purchases": [],
    "quits": [],
}
END = {"status": "finished", "iterations": 1, "price": 5.01, "n_available": 2, "n_initial": 2}
STATE = {"id": 7, "status": "finished", "history": [ITERATION]}
NOT_FOUND = json.dumps({"detail": [{"loc": ["path"], "msg": "not found", "type": "not_found"}]})
NOT_FOUND = NOT_FOUND.encode()
"""An srd server's 404."""
Answer = tuple[int, str, bytes]
"""A fake server's answer: status, Content-Type, body."""


def stream(*events: tuple[str, str]) -> Answer:
    """An event stream of (name, data) events, as the fake server sends it."""
    body = "".join(f"event: {name}\ndata: {data}\n\n" for name, data in events)
    return 200, "text/event-stream", b": auction 7\n\n" + body.encode()


def as_json(value: Any) -> Answer:
    return 200, "application/json", json.dumps(value).encode()


class FakeServer(BaseHTTPRequestHandler):
    """Answers each path from ``answers``; with ``hold``, an event stream sends keep-alives until
    the client goes (and sets ``connected``). Records the paths asked."""

    hold: ClassVar[bool] = False
    answers: ClassVar[dict[str, Answer]] = {}
    asked: ClassVar[list[str]] = []
    connected: ClassVar[threading.Event] = threading.Event()

    def do_GET(self) -> None:
        path = self.path.partition("?")[0]  # srd watch asks for the rounds too
        self.asked.append(path)
        if path.endswith("/events") and self.hold:
            self._hold()
            return
        status, kind, body = self.answers.get(path, (404, "application/json", NOT_FOUND))
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def _hold(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.end_headers()
        self.connected.set()
        try:
            for _ in range(600):  # two minutes at most
                self.wfile.write(b": keep-alive\n\n")
                self.wfile.flush()
                time.sleep(0.2)
        except OSError:  # the client went away
            pass

    def log_message(self, format: str, *args: Any) -> None:  # quiet
        pass


@pytest.fixture
def fake() -> Iterator[tuple[str, type[FakeServer]]]:
    """A server on the loopback that is not an srd server: its URL and its handler class."""
    handler = type(
        "Handler", (FakeServer,), {"answers": {}, "asked": [], "connected": threading.Event()}
    )
    with serving(handler, HOST) as url:
        yield url, handler


def watch(*args: str, env: dict[str, str] | None = None) -> Result:
    return CliRunner().invoke(cli, ["watch", *args], env=env)


# --- srd watch: a server that is not an srd server is exit 3, "could not follow" ---------------


@pytest.mark.parametrize(
    ("events", "words"),
    [
        ([("iteration", "<html>not json</html>")], "iteration: not JSON: '<html>not json</html>'"),
        (
            [("iteration", json.dumps({k: v for k, v in ITERATION.items() if k != "votes"}))],
            "iteration: votes is missing",
        ),
        ([("iteration", "[1, 2, 3]")], "iteration: the data is a list, not an object"),
        ([("iteration", json.dumps({**ITERATION, "price": "5"}))], "price is text, not a finite"),
        ([("iteration", json.dumps(ITERATION).replace("5.0,", "NaN,"))], "price is NaN"),
        (
            [
                (
                    "iteration",
                    json.dumps({**ITERATION, "votes": {"buy": True, "hold": 0, "quit": 0}}),
                )
            ],
            "votes.buy is a boolean, not a whole number",
        ),
        (
            [("iteration", json.dumps({**ITERATION, "purchases": [{"participant": "a"}]}))],
            "purchases[0].version is missing",
        ),
        ([("round", json.dumps({"round": "one"}))], "round: round is text"),
        ([("end", "{}")], "end: status is missing"),
        ([("end", json.dumps({**END, "iterations": None}))], "end: iterations is null"),
    ],
)
@pytest.mark.parametrize("json_output", [False, True])
def test_watch_of_events_no_srd_server_sends_exits_3_saying_so(
    fake: tuple[str, type[FakeServer]], events: list[tuple[str, str]], words: str, json_output: bool
) -> None:
    url, handler = fake
    handler.answers = {"/auctions/7/events": stream(*events), "/auctions/7": as_json(STATE)}
    result = watch("7", "--server", url, *(["--json"] if json_output else []))
    assert result.exit_code == 3, (result.output, result.exception)
    message = f"the server at {url} {NOT_SRD} event: "
    assert message in result.stderr and words in result.stderr
    assert "Traceback" not in result.stderr and "None" not in result.stdout
    if json_output:  # the failure as the one JSON object on stdout
        failure = json.loads(result.stdout)
        assert list(failure) == ["error"] and words in failure["error"]
    else:
        assert "finished after" not in result.stdout


@pytest.mark.parametrize(
    ("final", "words"),
    [
        ((200, "text/html", b"<html><body>hello</body></html>"), "not JSON: '<html><body>hello"),
        (as_json({}), "id is missing"),
        (as_json([STATE]), "the data is a list, not an object"),
        (as_json({**STATE, "id": 8}), "answered auction 8"),
    ],
)
def test_watch_json_of_a_final_state_no_srd_server_sends_exits_3(
    fake: tuple[str, type[FakeServer]], final: Answer, words: str
) -> None:
    """The end event is fine, ``GET /auctions/7`` is not what an srd server answers."""
    url, handler = fake
    handler.answers = {
        "/auctions/7/events": stream(
            ("iteration", json.dumps(ITERATION)), ("end", json.dumps(END))
        ),
        "/auctions/7": final,
    }
    result = watch("7", "--server", url, "--json")
    assert result.exit_code == 3, (result.output, result.exception)
    assert NOT_SRD in result.stderr and words in result.stderr
    assert words in json.loads(result.stdout)["error"]


def test_watch_of_a_page_that_is_not_an_event_stream_exits_3(
    fake: tuple[str, type[FakeServer]],
) -> None:
    url, handler = fake
    handler.answers = {"/auctions/7/events": (200, "text/html", b"<html>event: end</html>")}
    result = watch("7", "--server", url)
    assert result.exit_code == 3
    assert f"{NOT_SRD} event stream: /auctions/7/events is text/html" in result.stderr
    assert handler.asked == ["/auctions/7/events"]  # not taken for a dropped stream


def test_watch_skips_events_it_does_not_know_and_reads_a_sound_stream(
    fake: tuple[str, type[FakeServer]],
) -> None:
    url, handler = fake
    handler.answers = {
        "/auctions/7/events": stream(
            ("news", "not JSON, and not read"),
            ("iteration", json.dumps(ITERATION)),
            ("end", json.dumps(END)),
        ),
        "/auctions/7": as_json(STATE),
    }
    result = watch("7", "--server", url)
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines()[-1].startswith("auction 7 finished after 1 iteration: 0 of 2")
    done = watch("7", "--server", url, "--json")
    assert done.exit_code == 0 and json.loads(done.stdout) == STATE


# --- srd watch: the auction id and the server's URL ----------------------------------------------


@pytest.mark.parametrize("auction_id", [str(MAX_ROW_ID + 1), "99999999999999999999", "0"])
def test_watch_of_an_id_the_api_cannot_hold_is_a_usage_error(
    fake: tuple[str, type[FakeServer]], auction_id: str
) -> None:
    url, handler = fake
    result = watch(auction_id, "--server", url, "--json")
    assert result.exit_code == 2
    assert "AUCTION_ID" in result.stderr and f"1<=x<={MAX_ROW_ID}" in result.stderr
    assert "AUCTION_ID" in json.loads(result.stdout)["error"]
    assert handler.asked == []  # nothing was sent


def test_watch_of_the_largest_id_asks_the_server(fake: tuple[str, type[FakeServer]]) -> None:
    url, handler = fake
    result = watch(str(MAX_ROW_ID), "--server", url)
    assert result.exit_code == 3
    assert f"auction {MAX_ROW_ID} not found on {url}" in result.stderr
    assert handler.asked == [f"/auctions/{MAX_ROW_ID}/events"]


def test_watch_of_a_404_no_srd_server_sends_says_so(fake: tuple[str, type[FakeServer]]) -> None:
    url, handler = fake
    handler.answers = {"/auctions/1/events": (404, "text/html", b"<html>File not found</html>")}
    result = watch("1", "--server", url)
    assert result.exit_code == 3
    assert f"the server at {url} {NOT_SRD}" in result.stderr and "HTTP 404" in result.stderr
    assert "auction 1 not found" not in result.stderr


@pytest.mark.parametrize("command", ["agents", "watch"])
def test_a_server_url_whose_port_is_no_port_is_a_usage_error(command: str) -> None:
    args = ["--honest", "1", "--give-up", "1"] if command == "agents" else ["1"]
    result = CliRunner().invoke(cli, [command, *args, "--server", "http://127.0.0.1:99999"])
    assert result.exit_code == 2, (result.output, result.exception)  # agents: a traceback
    assert "99999 is no TCP port (1 to 65535)" in result.stderr
    assert "--server" in result.stderr and "Traceback" not in result.output


@pytest.mark.parametrize("command", ["agents", "watch"])
@pytest.mark.parametrize("url", ["http://ann:s3cret@127.0.0.1:9", "ftp://ann:s3cret@host"])
def test_a_server_url_with_credentials_is_refused_without_showing_the_password(
    command: str, url: str
) -> None:
    """A user and password in ``--server`` would take the header srd's bearer tokens go in:
    refused, and the refusal (echoed to a terminal or a log) masks the password."""
    args = ["--honest", "1", "--give-up", "1"] if command == "agents" else ["1"]
    result = CliRunner().invoke(cli, [command, *args, "--server", url, "--json"])
    assert result.exit_code == 2, (result.output, result.exception)
    assert "s3cret" not in result.output and "ann:***@" in result.stderr
    assert [e["option"] for e in json.loads(result.stdout)["errors"]] == ["--server"]


def test_agents_against_a_server_answering_html_errors_say_it_is_no_srd_server(
    fake: tuple[str, type[FakeServer]],
) -> None:
    """``POST /submit`` answered by a plain web server (501, an HTML page)."""
    url, _ = fake
    result = CliRunner().invoke(
        cli, ["agents", "--server", url, "--honest", "1", "--give-up", "2", "--json"]
    )
    assert result.exit_code == 1, result.output
    error = json.loads(result.stdout)["error"]
    assert "is it an srd server?" in error and "text/html" in error
    assert "<!DOCTYPE" not in error and len(error) < 300


@pytest.mark.parametrize("url", ["http://[::1", "http://[::1]:99999", "http://exa mple.org:x"])
def test_watch_of_a_url_httpx_refuses_is_a_usage_error_naming_server(url: str) -> None:
    result = watch("1", "--server", url, "--json")
    assert result.exit_code == 2, (result.output, result.exception)
    assert "--server" in result.stderr and "Traceback" not in result.stderr
    assert [e["option"] for e in json.loads(result.stdout)["errors"]] == ["--server"]


@pytest.mark.parametrize("value", ["garbage", "http://[::1"])
def test_watch_names_srd_url_when_the_bad_url_came_from_it(value: str) -> None:
    result = watch("1", env={"SRD_URL": value})
    assert result.exit_code == 2, (result.output, result.exception)
    assert "Invalid value for SRD_URL (for --server)" in result.stderr
    given = watch("1", "--server", value, env={"SRD_URL": "http://127.0.0.1:9"})
    assert given.exit_code == 2 and "SRD_URL" not in given.stderr  # the option's own value
    assert "Invalid value for '--server'" in given.stderr


# --- NaN and infinities are no number an option takes --------------------------------------------


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "NaN"])
@pytest.mark.parametrize(
    ("args", "option"),
    [
        (["screen", "x.json", "--margin"], "--margin"),
        (["healthcheck", "--timeout"], "--timeout"),
        (["watch", "1", "--reconnect-s"], "--reconnect-s"),  # NaN: reconnected without a pause
    ],
)
def test_a_non_finite_number_is_a_usage_error_naming_the_option(
    args: list[str], option: str, value: str
) -> None:
    result = CliRunner().invoke(cli, [*args, value])
    assert result.exit_code == 2, (result.output, result.exception)
    assert option in result.stderr and "is not a finite number" in result.stderr


def test_healthcheck_says_its_timeout_is_in_seconds() -> None:
    result = CliRunner().invoke(cli, ["healthcheck", "--help"])
    assert result.exit_code == 0 and "Seconds" in result.output


# --- srd healthcheck: SRD_HOST ------------------------------------------------------------------


def healthcheck(host: str, port: int) -> subprocess.CompletedProcess[str]:
    """``srd healthcheck --timeout 2`` in a process with SRD_HOST and SRD_PORT set."""
    env = {**os.environ, "SRD_HOST": host, "SRD_PORT": str(port)}
    return subprocess.run(
        [*srd_command(), "healthcheck", "--timeout", "2"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )


@pytest.mark.parametrize("host", ["127.0.0.77:18771", "[::1", "::1]", "a/b", "a b", "x@y", "a?b"])
def test_healthcheck_of_a_host_that_is_no_host_exits_1_naming_srd_host(host: str) -> None:
    done = healthcheck(host, 18771)
    assert done.returncode == 1
    assert done.stderr == f"srd healthcheck: SRD_HOST={host}: not a host name or address\n"


@pytest.mark.parametrize("host", ["[::1]", "::1"])
def test_healthcheck_asks_an_ipv6_host_in_one_pair_of_brackets(
    fake: tuple[str, type[FakeServer]], host: str
) -> None:
    port = int(fake[0].rsplit(":", 1)[1])  # listens on 127.0.0.1: nobody on [::1] at this port
    done = healthcheck(host, port)
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr.startswith(f"http://[::1]:{port}/healthz: ")


def test_healthcheck_of_a_ready_server_exits_0(fake: tuple[str, type[FakeServer]]) -> None:
    url, handler = fake
    handler.answers = {"/healthz": as_json({"status": "ok", "problems": []})}
    port = int(url.rsplit(":", 1)[1])
    for host in (HOST, "0.0.0.0", "[::]"):  # every interface: the loopback is asked
        done = healthcheck(host, port)
        assert done.returncode == 0, done.stderr
        assert done.stdout == f"http://{HOST}:{port}/healthz: 200\n"


@pytest.mark.parametrize(
    "answer",
    [
        (200, "text/html", b"<html>It works!</html>"),  # a web server's page on the address
        as_json({"status": "starting"}),
        as_json(["ok"]),
    ],
)
def test_healthcheck_of_a_200_that_is_no_ready_answer_exits_1(
    fake: tuple[str, type[FakeServer]], answer: Answer
) -> None:
    url, handler = fake
    handler.answers = {"/healthz": answer}
    done = healthcheck(HOST, int(url.rsplit(":", 1)[1]))
    assert done.returncode == 1, done.stdout
    assert done.stderr.endswith(": 200, but no srd readiness answer (no status ok)\n")


# --- srd screen: the file as POST /submit takes it, under the settings srd serve takes ---------


def manifest_text(name: str = "inputs") -> str:
    return honest_manifest(np.random.default_rng(0), name).model_dump_json()


def test_screen_of_an_endless_file_reads_only_what_submit_takes() -> None:
    done = subprocess.run(
        [*srd_command(), "screen", "/dev/zero", "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert done.returncode == 2, done.stderr
    error = json.loads(done.stdout)["errors"][0]["message"]
    assert error == (
        "/dev/zero: larger than 262144 bytes, the most POST /submit takes (SRD_MAX_BODY_BYTES)"
    )


def test_screen_of_a_pipe_reads_what_its_writer_sends_in_pieces() -> None:
    """A pipe is read until its writer closes it, however it cuts the manifest up and however
    long it pauses; what comes is screened as the file would be."""
    text = manifest_text().encode()
    process = subprocess.Popen(
        [*srd_command(), "screen", "/dev/stdin", "--json"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=ROOT,
    )
    try:
        assert process.stdin is not None
        third = len(text) // 3
        for piece in (text[:third], text[third : 2 * third], text[2 * third :]):
            process.stdin.write(piece)
            process.stdin.flush()
            time.sleep(0.6)  # longer than the read's wake-up: it waits on, does not stop
        stdout, stderr = process.communicate(timeout=120)
    finally:
        process.kill()
        process.wait()
    assert process.returncode == 0, stderr
    assert json.loads(stdout)["status"] == "accepted"


def test_screen_refuses_a_padded_manifest_larger_than_the_configured_body_limit(
    tmp_path: Path,
) -> None:
    padded = tmp_path / "padded.json"
    padded.write_text(manifest_text() + " " * 400_000)  # valid JSON: white space after it
    size = padded.stat().st_size
    outcome = CliRunner().invoke(cli, ["screen", str(padded), "--json"])
    assert outcome.exit_code == 2
    assert "larger than 262144 bytes" in outcome.stderr and "SRD_MAX_BODY_BYTES" in outcome.stderr
    assert json.loads(outcome.stdout)["accepted"] is False
    allowed = CliRunner().invoke(
        cli, ["screen", str(padded), "--json"], env={"SRD_MAX_BODY_BYTES": str(size)}
    )
    assert allowed.exit_code == 0, allowed.output  # exactly the limit: taken, as /submit takes it
    smaller = CliRunner().invoke(
        cli, ["screen", str(padded)], env={"SRD_MAX_BODY_BYTES": str(size - 1)}
    )
    assert smaller.exit_code == 2 and f"larger than {size - 1} bytes" in smaller.stderr


@pytest.mark.parametrize(
    ("variable", "value", "words"),
    [
        ("SRD_MAX_BODY_BYTES", "lots", "SRD_MAX_BODY_BYTES=lots: Input should be a valid integer"),
        ("SRD_MAX_BODY_BYTES", "10", "SRD_MAX_BODY_BYTES=10: Input should be greater than"),
        ("SRD_SCREENER_SECRET", "short", "SRD_SCREENER_SECRET: "),
        ("SRD_SCREENER_SECRET", "a" * 40, "SRD_SCREENER_SECRET: "),
        ("SRD_SCREENER_SECRET", " " * 3, "SRD_SCREENER_SECRET: "),
        ("SRD_SCREENER_SECRET", "\udce9" * 40, "SRD_SCREENER_SECRET: "),  # 40 × the byte 0xe9
        ("SRD_MAX_BODY_BYTES", "\udce9", "SRD_MAX_BODY_BYTES=\ufffd: Input should be a valid"),
    ],
)
def test_screen_refuses_a_setting_srd_serve_refuses_naming_it(
    tmp_path: Path, variable: str, value: str, words: str
) -> None:
    path = tmp_path / "m.json"
    path.write_text(manifest_text())
    for extra in ([], ["--json"]):
        outcome = CliRunner().invoke(cli, ["screen", str(path), *extra], env={variable: value})
        assert outcome.exit_code == 2, (outcome.output, outcome.exception)
        assert words in outcome.stderr
        assert "Value error" not in outcome.stderr  # the validator's own words, as srd serve's
        if variable == "SRD_SCREENER_SECRET":
            assert "at least 32 characters, 10 of them different" in outcome.stderr
            assert "short" not in outcome.stderr and "a" * 40 not in outcome.stderr  # unsaid
        if extra:
            assert words in json.loads(outcome.stdout)["error"]


def test_screen_of_an_integer_beyond_the_float_range_names_its_path(tmp_path: Path) -> None:
    data = json.loads(manifest_text())
    data["external_sensor"]["PG"]["weights"]["price"] = 10**400
    path = tmp_path / "huge.json"
    path.write_text(json.dumps(data))
    where = "external_sensor.PG.weights.price"
    outcome = CliRunner().invoke(cli, ["screen", str(path), "--json"])
    assert outcome.exit_code == 2, (outcome.output, outcome.exception)
    assert f"{where}: out of range: not a finite float" in outcome.stderr
    errors = json.loads(outcome.stdout)["errors"]
    assert [e["path"] for e in errors] == [where] and "out of range" in errors[0]["message"]


# --- srd serve: a host to bind, a Ray cluster that answers ---------------------------------------


@pytest.mark.parametrize("host", ["", " ", "\t"])
def test_serve_refuses_an_empty_host_naming_the_option(host: str) -> None:
    result = CliRunner().invoke(cli, ["serve", "--host", host])
    assert result.exit_code == 2, (result.output, result.exception)
    assert "Invalid value for '--host'" in result.stderr
    assert "cannot be empty or white space" in result.stderr


def serve(tmp_path: Path, **variables: str) -> subprocess.CompletedProcess[str]:
    """``srd serve --port 0`` on a fresh SQLite file with these extra variables set."""
    env = {
        **os.environ,
        "SRD_DATABASE_URL": f"sqlite:///{tmp_path / 'srd.db'}",
        "SRD_DATA_DIR": str(tmp_path / "data"),
        "SRD_ADMIN_TOKEN": ADMIN_TOKEN,
        **variables,
    }
    return subprocess.run(
        [*srd_command(), "serve", "--port", "0"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )


def test_serve_refuses_a_blank_srd_host_naming_it(tmp_path: Path) -> None:
    done = serve(tmp_path, SRD_HOST="   ")
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("srd serve: SRD_HOST=")
    assert "cannot be empty or white space" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "srd.db").exists()


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray is not installed")
def test_serve_on_a_ray_address_nobody_answers_exits_3_naming_it(tmp_path: Path) -> None:
    with socket.socket() as held:  # bound, not listening: the connection is refused
        held.bind((HOST, 0))
        address = f"{HOST}:{held.getsockname()[1]}"
        started = time.monotonic()
        done = serve(tmp_path, SRD_JOB_BACKEND="ray", SRD_RAY_ADDRESS=address)
        elapsed = time.monotonic() - started
    assert done.returncode == 3, done.stderr
    assert done.stderr.startswith(f"srd serve: cannot join the Ray cluster at '{address}'")
    assert "(SRD_RAY_ADDRESS)" in done.stderr and "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert elapsed < 15  # refused at once, not after SRD_RAY_JOIN_TIMEOUT_S (30 s)
    assert not (tmp_path / "srd.db").exists()  # nothing stored


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray is not installed")
def test_serve_on_an_address_that_answers_but_is_no_ray_cluster_exits_3_naming_it(
    tmp_path: Path,
) -> None:
    """A web server where the Ray head should be: Ray's own join waits for ever (seen: over 5
    minutes); the start gives up after SRD_RAY_JOIN_TIMEOUT_S in one line (it ended in
    uvicorn's lifespan traceback)."""
    with serving(FakeServer, HOST) as url:
        address = url.removeprefix("http://")
        done = serve(
            tmp_path, SRD_JOB_BACKEND="ray", SRD_RAY_ADDRESS=address, SRD_RAY_JOIN_TIMEOUT_S="3"
        )
    assert done.returncode == 3, done.stderr
    assert done.stderr.strip() == (
        f"srd serve: cannot join the Ray cluster at '{address}' (SRD_RAY_ADDRESS): "
        "no answer within 3 s (SRD_RAY_JOIN_TIMEOUT_S)"
    )
    assert not (tmp_path / "srd.db").exists()  # nothing stored


def test_serve_on_a_port_in_use_exits_3_naming_it_before_it_makes_anything(
    tmp_path: Path,
) -> None:
    """A port another program listens on: one line naming the address and the options, exit
    3, before any database or operator token is made (uvicorn found it out after the app had
    started, said it in its own words and left its start-up behind)."""
    env = {
        **os.environ,
        "SRD_DATABASE_URL": f"sqlite:///{tmp_path / 'srd.db'}",
        "SRD_DATA_DIR": str(tmp_path / "data"),
    }
    env.pop("SRD_ADMIN_TOKEN", None)
    with socket.socket() as taken:
        taken.bind((HOST, 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = subprocess.run(
            [*srd_command(), "serve", "--host", HOST, "--port", str(port)],
            env=env, capture_output=True, text=True, timeout=120, cwd=ROOT,
        )  # fmt: skip
    assert done.returncode == 3, done.stderr
    assert done.stderr.strip() == (
        f"srd serve: cannot listen on {HOST}:{port} (--host/--port, SRD_HOST/SRD_PORT): "
        "Address already in use"
    )
    assert not (tmp_path / "srd.db").exists()
    assert not (tmp_path / "data").exists()  # nor its data folder


# --- Experiment list options: the element at fault, by its position -----------------------------


@pytest.mark.parametrize(
    ("command", "option"),
    [
        ("cheetah", "--backswing"),
        ("cheetah", "--inhibitor"),
        ("cheetah", "--lr"),
        ("auction-study", "--rarities"),
        ("comparison", "--rarities"),
    ],
)
@pytest.mark.parametrize(
    ("value", "words"),
    [
        ("0.5,,0.25", "element 2 of '0.5,,0.25' is empty"),
        ("0.5,0.25,", "element 3 of '0.5,0.25,' is empty"),
        ("0.5,0.25,x", "element 3 of '0.5,0.25,x': 'x' is not a number"),
        ("true,0.5", "element 1 of 'true,0.5': 'true' is not a number"),
        ("0.5,-101", "element 2 of '0.5,-101' (-101): Input should be greater than"),
    ],
)
def test_a_list_option_names_the_element_at_fault(
    tmp_path: Path, command: str, option: str, value: str, words: str
) -> None:
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, [command, option, value, "--json", "--out", str(out)])
    assert result.exit_code == 2, (result.output, result.exception)
    assert f"error: {option}: {words}" in result.stderr
    assert result.stderr.count("error:") == 1, result.stderr
    failure = json.loads(result.stdout)
    assert failure["errors"][0]["option"] == option and words in failure["errors"][0]["message"]
    assert not out.exists()


# --- Ctrl-C: exit 130, "Aborted!" (and under --json, the failure as one object) ---------------


def interrupted(process: subprocess.Popen[str]) -> tuple[int, str, str]:
    """SIGINT ``process`` (already waiting on something), then its exit code and output."""
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=60)
    return process.returncode, stdout, stderr


@pytest.mark.parametrize("json_output", [False, True])
def test_an_interrupted_watch_exits_130(
    fake: tuple[str, type[FakeServer]], json_output: bool
) -> None:
    """Under --json it is started as a script's background job is (``srd watch 7 &``, SIGINT
    ignored): an interrupt stops it all the same."""
    url, handler = fake
    handler.hold = True
    extra = ["--json"] if json_output else []
    process = subprocess.Popen(
        [*srd_command(), "watch", "7", "--server", url, *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        preexec_fn=(lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if json_output else None,
    )
    try:
        assert handler.connected.wait(60), "srd watch never connected"
        code, stdout, stderr = interrupted(process)
    finally:
        process.kill()
        process.wait()
    assert code == INTERRUPTED, stderr
    assert "Aborted!" in stderr and "Traceback" not in stderr
    assert (json.loads(stdout) if json_output else stdout) == (
        {"error": "aborted"} if json_output else ""
    )


@pytest.mark.parametrize(
    ("sig", "exit_code"), [(signal.SIGINT, INTERRUPTED), (signal.SIGTERM, TERMINATED)]
)
def test_a_screen_stopped_by_a_signal_prints_its_failure(
    tmp_path: Path, sig: signal.Signals, exit_code: int
) -> None:
    """``srd screen`` of a named pipe waits for its writer: stopped there by Ctrl-C (SIGINT,
    exit 130) or by ``kill`` or ``timeout`` (SIGTERM, exit 143, the same way out: before, the
    process died at once, with nothing on stdout), "Aborted!" and under ``--json`` the failure
    as one object."""
    fifo = tmp_path / "manifest.json"
    os.mkfifo(fifo)
    process = subprocess.Popen(
        [*srd_command(), "screen", str(fifo), "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    opened: list[int] = []
    opener = threading.Thread(target=lambda: opened.append(os.open(fifo, os.O_WRONLY)))
    opener.daemon = True
    opener.start()
    try:
        opener.join(120)  # returns once srd screen has opened the pipe to read it
        assert opened, "srd screen never opened the file"
        process.send_signal(sig)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        process.kill()
        process.wait()
        for fd in opened:
            os.close(fd)
    assert process.returncode == exit_code, stderr
    assert "Aborted!" in stderr and "Traceback" not in stderr
    assert json.loads(stdout) == {"accepted": False, "reasons": [], "error": "aborted"}


def test_a_server_stopped_by_ctrl_c_exits_130(tmp_path: Path) -> None:
    server = ServerProcess(
        database_url=f"sqlite:///{tmp_path / 'srd.db'}",
        data_dir=tmp_path / "data",
        admin_token=ADMIN_TOKEN,
    )
    with server:
        assert server.process is not None
        server.process.send_signal(signal.SIGINT)
        assert server.process.wait(60) == INTERRUPTED
    log = server.log_path.read_text()
    assert "Aborted!" in log and "Traceback" not in log


@pytest.mark.parametrize("name", [".", "..", "-", "_-"])
def test_screen_refuses_a_name_of_separators_as_the_server_does(tmp_path: Path, name: str) -> None:
    """POST /submit refuses it (422 at participant), so srd screen does too (exit 2)."""
    manifest = json.loads((ROOT / "examples" / "honest.json").read_text())
    path = tmp_path / "dots.json"
    path.write_text(json.dumps({**manifest, "participant": name}))
    result = CliRunner().invoke(cli, ["screen", str(path), "--json"])
    assert result.exit_code == 2, result.output
    assert json.loads(result.stdout)["error"].startswith("participant: a participant's name")
