"""The floor of an upload's CPU on this machine: parsing a fine-tuned manifest and one insert.

The capacity budget (``benchmarks/capacity.py``: 1 ms of server CPU per upload over round
sockets, 2 ms over long poll + PUT) was set on a machine where "parsing and one insert" cost
0.23-0.26 ms. This measures the same floor here, so the capacity figures can be read in that
machine's units: the manifest's strict parse (``parse_manifest_json``) and its digest, then one
transaction that inserts the upload's row (its digest, size, arrival and manifest JSON) into a
SQLite file in WAL mode, through SQLAlchemy Core and through the ``sqlite3`` module alone.
Nothing else runs in the process; CPU time, best of ``--repeats`` runs of ``--uploads``.

    .venv/bin/python benchmarks/upload_floor.py
"""

from __future__ import annotations

import argparse
import hashlib
import sqlite3
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from sqlalchemy import (
    Column,
    DateTime,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    create_engine,
    event,
)

from agents.manifest import parse_manifest_json
from agents.negotiator import honest_manifest

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
)


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
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="srd-floor-") as folder:
        _measure(Path(folder), args.uploads, args.repeats)


def _measure(folder: Path, uploads: int, repeats: int) -> None:
    body = honest_manifest(np.random.default_rng(0), "floor").model_dump_json().encode()
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

    print(f"manifest {len(body)} bytes; CPU ms per upload, best of {repeats} x {uploads}")
    for name, call in (
        ("parse + digest", parse),
        ("parse + digest + one insert (SQLAlchemy Core)", core),
        ("parse + digest + one insert (sqlite3)", plain),
    ):
        print(f"{name:>48}: {_best(call, uploads, repeats):.3f}")
    raw.close()
    engine.dispose()


if __name__ == "__main__":
    main()
