"""The floor of an upload's CPU on this machine: parsing a fine-tuned manifest and one insert,
and the floor of every piece the upload path's design requires.

The capacity budget (``benchmarks/capacity.py``: 1 ms of server CPU per upload over round
sockets, 2 ms over long poll + PUT) was set on a machine where "parsing and one insert" cost
0.23-0.26 ms. This measures the same floor here, so the capacity figures can be read in that
machine's units: the manifest's strict parse (``parse_manifest_json``) and its digest, then one
transaction that inserts the upload's row (its digest, size, arrival and manifest JSON) into a
SQLite file in WAL mode, through SQLAlchemy Core and through the ``sqlite3`` module alone.

Then the design's floor (docs/server.md's five steps), each piece the least code that does it
in this stack, nothing of the server's own logic (no token, patron, round or design check, no
live update, no lease):

- the transport: a FastAPI app on uvicorn (the server's stack, another process) that receives
  the manifest and answers a verdict-sized JSON, over one WebSocket (round sockets) and over
  HTTP PUT on a kept-alive connection (long poll + PUT); the server process's CPU per message;
- the two transactions the design asks for (stored on arrival, then the verdict recorded),
  each the fewest statements through SQLAlchemy Core: the round's row read and the upload
  inserted; the new version inserted and the upload's answer updated;
- the screener's round trip as the API pays it: the manifest's JSON sent down a pipe to
  another process and a small answer read back (the judging itself is the screener's cost);
- the auction step's share: the new version read back from its JSON and stacked into the
  market's batch (``from_manifests``), per patron of a 64-patron auction.

Nothing else runs in the process; CPU time, best of ``--repeats`` runs of ``--uploads``.

    .venv/bin/python benchmarks/upload_floor.py
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hashlib
import multiprocessing
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from multiprocessing.connection import Connection
from pathlib import Path

import httpx
import numpy as np
import uvicorn
from fastapi import FastAPI, Request, Response, WebSocket, WebSocketDisconnect
from sqlalchemy import (
    Column,
    DateTime,
    Engine,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    create_engine,
    event,
    select,
)
from websockets.asyncio.client import connect

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from agents.batch import from_manifests
from agents.manifest import Manifest, parse_manifest_json
from agents.negotiator import honest_manifest
from tests.support.processes import cpu_seconds

METADATA = MetaData()
UPLOADS = Table(
    "uploads",
    METADATA,
    Column("id", Integer, primary_key=True),
    Column("round_id", Integer, nullable=False),
    Column("position", Integer, nullable=False),
    Column("body_sha256", String(64), nullable=False),
    Column("bytes_in", Integer, nullable=False),
    Column("arrived", DateTime(timezone=True), nullable=False),
    Column("manifest", Text, nullable=False),
    Column("outcome", String(16), nullable=False, default="pending"),
    Column("answer", Text),
)
ROUNDS = Table(
    "rounds",
    METADATA,
    Column("id", Integer, primary_key=True),
    Column("status", String(16), nullable=False),
    Column("deadline", DateTime(timezone=True), nullable=False),
)
VERSIONS = Table(
    "versions",
    METADATA,
    Column("id", Integer, primary_key=True),
    Column("participant_id", Integer, nullable=False),
    Column("manifest", Text, nullable=False),
    Column("status", String(16), nullable=False),
    Column("created_at", DateTime(timezone=True), nullable=False),
)
ANSWER = b'{"round":1,"accepted":true,"reasons":[],"version":2,"model_id":7,"parent_id":6,' + (
    b'"uploaded_id":7,"outcome":"accepted"}'
)
"""An answer of the size a round's upload gets."""
MESSAGES = 5000
"""Messages per batch of a transport's measurement: the server's CPU is read in 10 ms ticks, and
5000 messages of about 0.07 ms are about 35 of them (the figure good to about 3 %)."""


def _wal(connection: sqlite3.Connection, _record: object) -> None:
    """The server's settings: WAL, durable across process crashes (not power losses)."""
    connection.execute("PRAGMA journal_mode=WAL")
    connection.execute("PRAGMA synchronous=NORMAL")


def _best(call: Callable[[int], None], uploads: int, repeats: int) -> float:
    """CPU ms per upload, best of ``repeats`` runs of ``uploads``."""
    call(0)  # warm-up
    runs = []
    for _ in range(repeats):
        start = time.process_time()
        for i in range(uploads):
            call(i)
        runs.append((time.process_time() - start) / uploads * 1e3)
    return min(runs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--uploads", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--serve", type=int, metavar="PORT", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        _serve(args.serve)
        return
    body = honest_manifest(np.random.default_rng(0), "floor").model_dump_json().encode()
    with tempfile.TemporaryDirectory(prefix="srd-floor-") as folder:
        print(f"manifest {len(body)} bytes; CPU ms per upload, best of {args.repeats} runs")
        parse_ms = _measure(Path(folder), body, args.uploads, args.repeats)
        _design_floor(Path(folder), body, parse_ms, args.uploads, args.repeats)


def _measure(folder: Path, body: bytes, uploads: int, repeats: int) -> float:
    """The budget's floor: the parse alone, and with one insert (Core, then sqlite3); the
    parse's figure."""
    engine = create_engine(f"sqlite:///{folder / 'core.db'}")
    event.listen(engine, "connect", _wal)
    METADATA.create_all(engine)
    insert = UPLOADS.insert()

    def parse(_: int) -> tuple[str, str]:
        manifest = parse_manifest_json(body)
        return hashlib.sha256(body).hexdigest(), manifest.model_dump_json()

    def core(i: int) -> None:
        digest, text = parse(i)
        with engine.begin() as connection:
            connection.execute(
                insert,
                {
                    "round_id": 1,
                    "position": i,
                    "body_sha256": digest,
                    "bytes_in": len(body),
                    "arrived": datetime.now(UTC),
                    "manifest": text,
                },
            )

    raw = sqlite3.connect(folder / "raw.db", isolation_level=None)
    _wal(raw, None)
    raw.execute(
        "CREATE TABLE uploads (id INTEGER PRIMARY KEY, round_id INTEGER, position INTEGER, "
        "body_sha256 TEXT, bytes_in INTEGER, arrived TEXT, manifest TEXT)"
    )

    def plain(i: int) -> None:
        digest, text = parse(i)
        raw.execute("BEGIN IMMEDIATE")
        raw.execute(
            "INSERT INTO uploads (round_id, position, body_sha256, bytes_in, arrived, manifest) "
            "VALUES (?, ?, ?, ?, ?, ?)",
            (1, i, digest, len(body), datetime.now(UTC).isoformat(), text),
        )
        raw.execute("COMMIT")

    figures = {}
    for name, call in (
        ("parse + digest", parse),
        ("parse + digest + one insert (SQLAlchemy Core)", core),
        ("parse + digest + one insert (sqlite3)", plain),
    ):
        figures[name] = _best(call, uploads, repeats)
        print(f"{name:>52}: {figures[name]:.3f}")
    raw.close()
    engine.dispose()
    return figures["parse + digest"]


def _design_floor(folder: Path, body: bytes, parse_ms: float, uploads: int, repeats: int) -> None:
    """Each piece the design requires, at its least, and their sums per transport."""
    print("\nthe design's floor, piece by piece:")
    engine = create_engine(f"sqlite:///{folder / 'design.db'}")
    event.listen(engine, "connect", _wal)
    METADATA.create_all(engine)
    pieces = {
        "round socket: receive the manifest, send the answer": _transport(body, "websocket"),
        "PUT: receive the manifest, send the answer": _transport(body, "http"),
        "parse + digest": parse_ms,
        "transaction 1: read the round, store the upload": _best(
            _stored(engine, body), uploads, repeats
        ),
        "transaction 2: insert the version, answer the upload": _best(
            _judged(engine, body), uploads, repeats
        ),
        "the screener's round trip (the API's side)": _screener_trip(body, uploads, repeats),
        "the auction step's share: the version into the market": _step_share(body, repeats),
    }
    engine.dispose()
    for name, ms in pieces.items():
        print(f"{name:>56}: {ms:.3f}")
    shared = sum(ms for name, ms in pieces.items() if not name.endswith("send the answer"))
    for name, budget in (
        ("round socket: receive the manifest, send the answer", 1.0),
        ("PUT: receive the manifest, send the answer", 2.0),
    ):
        total = shared + pieces[name]
        print(f"{'sum over ' + name.split(':')[0]:>56}: {total:.3f} (budget {budget:g})")


def _stored(engine: Engine, body: bytes) -> Callable[[int], None]:
    """Transaction 1: the round's status and deadline read, the upload inserted pending."""
    with engine.begin() as connection:
        connection.execute(
            ROUNDS.insert(),
            {"id": 1, "status": "open", "deadline": datetime(2100, 1, 1, tzinfo=UTC)},
        )
    read = select(ROUNDS.c.status, ROUNDS.c.deadline).where(ROUNDS.c.id == 1)
    insert = UPLOADS.insert()
    text = body.decode()

    def stored(i: int) -> None:
        with engine.begin() as connection:
            connection.execute(read).one()
            connection.execute(
                insert,
                {
                    "round_id": 1,
                    "position": i,
                    "body_sha256": "0" * 64,
                    "bytes_in": len(body),
                    "arrived": datetime.now(UTC),
                    "manifest": text,
                },
            )

    return stored


def _judged(engine: Engine, body: bytes) -> Callable[[int], None]:
    """Transaction 2: the new version inserted, the upload's answer written."""
    insert = VERSIONS.insert()
    update = UPLOADS.update().where(UPLOADS.c.id == 1)
    text, answer = body.decode(), ANSWER.decode()

    def judged(_: int) -> None:
        with engine.begin() as connection:
            connection.execute(
                insert,
                {
                    "participant_id": 1,
                    "manifest": text,
                    "status": "accepted",
                    "created_at": datetime.now(UTC),
                },
            )
            connection.execute(update, {"outcome": "accepted", "answer": answer})

    return judged


def _echo(conn: Connection) -> None:
    """The screener's stand-in: a small answer for every manifest, until the pipe closes."""
    while True:
        try:
            conn.recv_bytes()
        except EOFError:
            return
        conn.send((True, [], []))


def _screener_trip(body: bytes, uploads: int, repeats: int) -> float:
    """The manifest's JSON down a pipe to another process, its answer back: this side's CPU."""
    ours, theirs = multiprocessing.Pipe()
    process = multiprocessing.get_context("spawn").Process(target=_echo, args=(theirs,))
    process.start()

    def trip(_: int) -> None:
        ours.send_bytes(body)
        ours.recv()

    try:
        return _best(trip, uploads, repeats)
    finally:
        ours.close()
        process.join(timeout=10)


def _step_share(body: bytes, repeats: int) -> float:
    """One patron's share of restoring a 64-patron market: its version's JSON read back and
    stacked into the batch."""
    texts = [body.decode()] * 64

    def restore(_: int) -> None:
        from_manifests([Manifest.model_validate_json(text) for text in texts])

    return _best(restore, 20, repeats) / 64


def _serve(port: int) -> None:
    """The transport's stand-in server: the server's stack, no logic."""
    app = FastAPI()

    @app.websocket("/socket")
    async def echo_socket(websocket: WebSocket) -> None:
        await websocket.accept()
        with contextlib.suppress(WebSocketDisconnect):
            while True:
                await websocket.receive_text()
                await websocket.send_text(ANSWER.decode())

    @app.put("/upload")
    async def upload(request: Request) -> Response:
        await request.body()
        return Response(ANSWER, media_type="application/json")

    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning", ws_max_size=1 << 20)


def _transport(body: bytes, kind: str) -> float:
    """Server CPU ms per message: ``MESSAGES`` uploads one after another, over one WebSocket
    or over HTTP PUT on a kept-alive connection (best of three batches)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen([sys.executable, __file__, "--serve", str(port)])
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if time.monotonic() > deadline or server.poll() is not None:
                    raise RuntimeError("the stand-in server did not start") from None
                time.sleep(0.1)
        return asyncio.run(_drive(server.pid, port, body, kind))
    finally:
        server.terminate()
        server.wait(timeout=10)


async def _drive(pid: int, port: int, body: bytes, kind: str) -> float:
    text = body.decode()
    async with contextlib.AsyncExitStack() as stack:
        exchange: Callable[[], Awaitable[object]]
        if kind == "websocket":
            url = f"ws://127.0.0.1:{port}/socket"
            websocket = await stack.enter_async_context(connect(url, max_size=1 << 20))

            async def exchange() -> object:
                await websocket.send(text)
                return await websocket.recv()
        else:
            url = f"http://127.0.0.1:{port}"
            client = await stack.enter_async_context(httpx.AsyncClient(base_url=url))

            async def exchange() -> object:
                return (await client.put("/upload", content=body)).raise_for_status()

        best = float("inf")
        for _ in range(3):
            before = cpu_seconds(pid) or 0.0
            for _ in range(MESSAGES):
                await exchange()
            best = min(best, ((cpu_seconds(pid) or 0.0) - before) / MESSAGES * 1e3)
    return best


if __name__ == "__main__":
    main()
