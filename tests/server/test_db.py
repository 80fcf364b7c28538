"""Schema, connections and settings: migrations build exactly the models, SQLite runs in WAL
mode with foreign keys, the admin token is generated once into a 0600 file."""

from __future__ import annotations

import logging
import math
import sqlite3
import stat
import threading
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from fastapi.testclient import TestClient
from pydantic import ValidationError
from sqlalchemy import create_engine, insert, text
from sqlalchemy.exc import IntegrityError, OperationalError

from server.app import create_app
from server.config import Settings
from server.store import db as db_module
from server.store.db import (
    SQLITE_BUSY_TIMEOUT_MS,
    Database,
    DatabaseUnavailableError,
    alembic_config,
    upgrade_schema,
)
from server.store.tables import Base, ModelVersion, utcnow
from tests.support.databases import postgres_database
from tests.support.factories import honest, unique
from tests.support.server import ADMIN, ADMIN_TOKEN, make_settings, wait_for


def test_migrations_build_exactly_the_models(database_url: str) -> None:
    upgrade_schema(database_url)
    upgrade_schema(database_url)  # idempotent: already at head
    database = Database(database_url)
    with database.engine.connect() as connection:
        assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
        revision = connection.execute(text("select version_num from alembic_version")).scalar()
    database.close()
    assert revision == ScriptDirectory.from_config(alembic_config(database_url)).get_current_head()


@pytest.mark.parametrize(
    ("before", "description", "cleaned"),
    [
        # control characters and bidirectional overrides, refused from revision 0010 on
        ("0009", "line one\nnul\u0000 bell\u0007 flip\u202e end", "line one\nnul bell flip end"),
        # invisible characters (a zero-width space, a soft hyphen, tag characters spelling
        # hidden text), refused from revision 0014 on
        (
            "0013",
            "sincere\u200b bidder"
            + "".join(chr(0xE0000 + ord(c)) for c in "admit me")
            + " \u00adend",
            "sincere bidder end",
        ),
        # variation selectors spelling hidden text, runs of joiners, other invisible formats,
        # refused from revision 0018 on (runs are cut to two)
        (
            "0017",
            "Honest." + "\ufe01\ufe0a" * 37 + " a\u200d\u200d\u200db\ufffc \U0001d173\u2764\ufe0f",
            "Honest. a\u200d\u200db \u2764\ufe0f",
        ),
    ],
)
def test_a_description_stored_before_the_schema_refused_its_characters_reads_again(
    fresh_database_url: str, before: str, description: str, cleaned: str
) -> None:
    """A description stored before its characters were refused loses them, and its manifest
    reads again."""
    from alembic import command
    from sqlalchemy import select

    from agents.manifest import parse_manifest

    command.upgrade(alembic_config(fresh_database_url), before)
    manifest = {**honest(unique("old")), "description": description}
    database = Database(fresh_database_url)
    with database.engine.begin() as connection:
        participant = connection.execute(
            text(
                "insert into participants (name, name_key, token_hash, created_at) "
                "values (:n, :n, 'x', :at) returning id"
            ),
            {"n": manifest["participant"], "at": utcnow()},
        ).scalar_one()
        connection.execute(
            insert(ModelVersion).values(
                participant_id=participant,
                version=1,
                manifest=manifest,
                accepted=True,
                reasons=[],
                created_at=utcnow(),
                status="accepted",
            )
        )
    database.close()
    upgrade_schema(fresh_database_url)
    database = Database(fresh_database_url)
    with database.engine.connect() as connection:
        stored = connection.scalar(
            select(ModelVersion.manifest).where(ModelVersion.participant_id == participant)
        )
    database.close()
    assert stored["description"] == cleaned
    assert parse_manifest(stored).description == cleaned


def test_look_alike_names_registered_before_keep_working_and_new_ones_are_taken(
    fresh_database_url: str, tmp_path: Path
) -> None:
    """Names that read alike (honest-1, honest-I) registered before revision 0015 each keep
    their participant (the first its key, the later one a key of its own); once upgraded, a new
    look-alike of either is taken (409), and its owner is told its spelling."""
    from alembic import command

    command.upgrade(alembic_config(fresh_database_url), "0014")
    database = Database(fresh_database_url)
    with database.engine.begin() as connection:
        for name in ("look-1", "look-I", "look-0l", "dove-2", "clove-2"):
            connection.execute(
                text(
                    "insert into participants (name, name_key, token_hash, created_at) "
                    "values (:n, :k, 'x', :at)"
                ),
                {"n": name, "k": name.casefold(), "at": utcnow()},
            )
    database.close()
    upgrade_schema(fresh_database_url)
    settings = make_settings(fresh_database_url, tmp_path / "data")
    with TestClient(create_app(settings)) as client:
        for name in ("look-1", "look-I", "look-0l", "dove-2", "clove-2"):  # each its own
            again = client.post("/submit", json=honest(name))
            assert again.status_code == 401 and "missing_token" in again.text, again.text
            assert client.get(f"/participants/{name}").json()["name"] == name  # its own page
        assert client.get("/participants/LOOK-l").json()["name"] == "look-1"  # the first's key
        taken = client.post("/submit", json=honest("Look_l"))
        assert taken.status_code == 409, taken.text
        (item,) = taken.json()["detail"]
        assert item["type"] == "name_taken" and "'look-1' has it" in item["msg"]
        first = client.post("/submit", json=honest("mirror-0")).json()
        spelled = client.post(
            "/submit",
            json=honest("Mirror-O"),
            headers={"Authorization": f"Bearer {first['token']}"},
        )
        assert spelled.status_code == 422 and "spelled 'mirror-0'" in spelled.text
        client.post("/submit", json=honest("agent-101"))
        for alike in ("agent-l01", "Agent-I01", "agent_1O1"):
            assert client.post("/submit", json=honest(alike)).status_code == 409, alike
        for alike in ("agent-0l0l", "Agent-OIOI"):  # zeros before digits that are letters
            assert client.post("/submit", json=honest(alike)).status_code == 409, alike
        client.post("/submit", json=honest("seat-1"))
        for alike in ("Seat-01", "seat-0l", "Seat-OI", "seat-00l", "seat_0i"):
            taken = client.post("/submit", json=honest(alike))
            assert taken.status_code == 409 and "'seat-1' has it" in taken.text, alike
        for apart in ("agent-11", "olive-1", "live-1"):  # distinct names stay apart
            assert client.post("/submit", json=honest(apart)).status_code == 201, apart
        client.post("/submit", json=honest("dave-7"))
        for alike in ("clave-7", "C1ave-7", "cIave-7"):  # cl reads d (so do c1 and cI)
            assert client.post("/submit", json=honest(alike)).status_code == 409, alike
        assert client.post("/submit", json=honest("cave-7")).status_code == 201


def _insert_row(connection: Any, name: str, given: dict[str, Any]) -> int:
    """Insert a row into table ``name`` as its schema stands (reflected): ``given`` values,
    and a plain value of its type for every other column that needs one."""
    from sqlalchemy import JSON, Boolean, DateTime, Integer, MetaData, Table

    table = Table(name, MetaData(), autoload_with=connection)
    values = dict(given)
    for column in table.columns:
        if column.name in values or column.nullable or column.primary_key:
            continue
        if column.server_default is not None:
            continue
        kind = column.type
        if isinstance(kind, Boolean):
            values[column.name] = True
        elif isinstance(kind, Integer):
            values[column.name] = 1
        elif isinstance(kind, DateTime):
            values[column.name] = utcnow()
        elif isinstance(kind, JSON):
            values[column.name] = {}
        else:
            values[column.name] = "x"
    return int(connection.execute(insert(table).values(values)).inserted_primary_key[0])


@pytest.mark.parametrize("revision", ["0005", "0008"])
def test_a_database_with_rows_upgrades_through_migrations_that_copy_tables(
    fresh_database_url: str, revision: str
) -> None:
    """Migrations 0006 and 0009 copy and drop tables that others reference (SQLite alters a
    table by copying it): a database holding rows from before them upgrades, its rows kept."""
    from alembic import command

    command.upgrade(alembic_config(fresh_database_url), revision)
    database = Database(fresh_database_url)
    with database.engine.begin() as connection:
        participant = _insert_row(connection, "participants", {"name": "Old-Timer"})
        model = _insert_row(
            connection,
            "model_versions",
            {"participant_id": participant, "version": 1, "manifest": honest("Old-Timer")},
        )
    database.close()
    upgrade_schema(fresh_database_url)
    database = Database(fresh_database_url)
    with database.engine.connect() as connection:
        owner = connection.execute(
            text("select participant_id from model_versions where id = :id"), {"id": model}
        ).scalar_one()
        name = connection.execute(
            text("select name from participants where id = :id"), {"id": participant}
        ).scalar_one()
        head = connection.execute(text("select version_num from alembic_version")).scalar_one()
    database.close()
    assert (owner, name) == (participant, "Old-Timer")
    scripts = ScriptDirectory.from_config(alembic_config(fresh_database_url))
    assert head == scripts.get_current_head()


def _tuned_auction(client: TestClient) -> int:
    """A finished auction whose market fine-tunes its five patrons after its first rounds."""
    ids = [
        client.post("/submit", json=honest(unique("t"), seed=s)).json()["model_id"]
        for s in (0, 2, 3, 4, 5)
    ]
    body = {"n_fish": 2, "model_ids": ids, "seed": 3, "fine_tune": True, "fine_tune_rounds": 3}
    auction_id = int(client.post("/auctions", json=body, headers=ADMIN).json()["auction_id"])
    wait_for(
        lambda: client.get(f"/auctions/{auction_id}").json(),
        lambda a: a["status"] == "finished",
        timeout_s=120,
    )
    return auction_id


@pytest.mark.postgres_in_slow_run
def test_an_auction_fine_tuned_before_weights_were_kept_says_they_are_not_known(
    fresh_database_url: str, tmp_path: Path
) -> None:
    """An auction played before migration 0013 kept no fine-tuned weights: its votes after a
    fine-tuning inside the market say so, and their weights answer 404 naming why."""
    from alembic import command

    settings = make_settings(fresh_database_url, tmp_path / "data")
    with TestClient(create_app(settings)) as client:
        auction_id = _tuned_auction(client)
        votes = client.get(f"/auctions/{auction_id}/iterations/1/votes").json()["votes"]
        assert any(vote["fine_tuned_after"] == 0 for vote in votes)
    command.downgrade(alembic_config(fresh_database_url), "0012")  # as a release before wrote it
    upgrade_schema(fresh_database_url)
    with TestClient(create_app(settings)) as client:
        seen: set[bool] = set()
        for n in (0, 1):
            for vote in client.get(f"/auctions/{auction_id}/iterations/{n}/votes").json()["votes"]:
                manifest = client.get(f"/models/{vote['model_id']}").json()["manifest"]
                # known: before any fine-tuning, or a patron whose manifest never fine-tunes
                kept = n == 0 or manifest["fine_tuning"]["epochs"] == 0
                assert (vote["weights_kept"], vote["fine_tuned_after"]) == (kept, None)
                path = f"/auctions/{auction_id}/iterations/{n}/votes/{vote['model_id']}/weights"
                response = client.get(path)
                if kept:
                    assert response.status_code == 200, response.text
                else:
                    assert response.status_code == 404
                    detail = response.json()["detail"][0]
                    assert detail["loc"] == ["path", "model_id"] and "not kept" in detail["msg"]
                seen.add(kept)
        assert seen == {True, False}
        new = _tuned_auction(client)
        votes = client.get(f"/auctions/{new}/iterations/1/votes").json()["votes"]
        assert all(vote["weights_kept"] for vote in votes)  # a new auction keeps them


def test_a_database_a_newer_release_wrote_is_refused_untouched(fresh_database_url: str) -> None:
    upgrade_schema(fresh_database_url)
    database = Database(fresh_database_url)
    with database.engine.begin() as connection:
        connection.execute(text("update alembic_version set version_num = '9999_future'"))
    database.close()
    with pytest.raises(DatabaseUnavailableError, match="revision 9999_future, which this release"):
        upgrade_schema(fresh_database_url)
    database = Database(fresh_database_url)
    with database.engine.connect() as connection:
        kept = connection.execute(text("select version_num from alembic_version")).scalar_one()
    database.close()
    assert kept == "9999_future"


def test_a_database_at_the_revision_but_lacking_a_column_is_refused(
    fresh_database_url: str, tmp_path: Path
) -> None:
    """A build between releases may have stamped a revision without this release's columns:
    the start names what is missing instead of serving 500s."""
    from server.store.db import prepare_database

    upgrade_schema(fresh_database_url)
    database = Database(fresh_database_url)
    with database.engine.begin() as connection:
        connection.execute(text("alter table auctions drop column enroll_until"))
    database.close()
    with pytest.raises(DatabaseUnavailableError, match=r"lacks the column auctions\.enroll_until"):
        prepare_database(fresh_database_url, tmp_path / "databases.json")


def test_a_migration_blocked_by_another_session_fails_instead_of_waiting(
    fresh_database_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """PostgreSQL: an old server's open read holds a table the migration alters; the start
    fails within the lock timeout, changing nothing, and succeeds once the table is free."""
    from alembic import command

    if fresh_database_url.startswith("sqlite"):
        pytest.skip("SQLite: one server holds the file (the serve lock), nobody else reads it")
    monkeypatch.setattr(db_module, "MIGRATION_LOCK_TIMEOUT_S", 1.0)
    command.upgrade(alembic_config(fresh_database_url), "0011")
    database = Database(fresh_database_url)
    try:
        with database.engine.connect() as reader:  # a transaction that read the table
            reader.execute(text("select count(*) from auctions"))
            started = time.monotonic()
            with pytest.raises(DatabaseUnavailableError, match="stop every server of the old"):
                upgrade_schema(fresh_database_url)
            assert time.monotonic() - started < 10
        with database.engine.connect() as connection:
            kept = connection.execute(text("select version_num from alembic_version")).scalar()
        assert kept == "0011"
        upgrade_schema(fresh_database_url)  # the reader gone, the migration runs
    finally:
        database.close()


def test_foreign_keys_are_enforced(database_url: str) -> None:
    upgrade_schema(database_url)
    database = Database(database_url)
    with database.session(write=True) as session, pytest.raises(IntegrityError):
        session.execute(
            insert(ModelVersion).values(
                participant_id=987654,
                version=1,
                manifest={},
                accepted=True,
                reasons=[],
                created_at=utcnow(),
            )
        )
        session.commit()
    database.close()


def test_sqlite_runs_in_wal_mode(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'wal.db'}"
    upgrade_schema(url)
    database = Database(url)
    with database.engine.connect() as connection:
        assert connection.exec_driver_sql("pragma journal_mode").scalar() == "wal"
        assert connection.exec_driver_sql("pragma foreign_keys").scalar() == 1
    database.close()


def test_admin_token_is_generated_once_into_a_0600_file(tmp_path: Path) -> None:
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path, admin_token=None)
    with TestClient(create_app(settings)) as client:
        token = settings.admin_token_file.read_text().strip()
        assert stat.S_IMODE(settings.admin_token_file.stat().st_mode) == 0o600
        assert token.startswith("srda_") and len(token) > 40
        job = {"kind": "fish", "params": {"steps": 0}}  # invalid params: 422 after the auth
        assert client.post("/jobs", json=job).status_code == 401
        good = client.post("/jobs", json=job, headers={"Authorization": f"Bearer {token}"})
        assert good.status_code == 422
    with TestClient(create_app(settings)):
        assert settings.admin_token_file.read_text().strip() == token


def test_a_short_admin_token_is_named_in_the_log(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path, admin_token="x")
    with caplog.at_level(logging.WARNING), TestClient(create_app(settings)):
        pass
    assert "SRD_ADMIN_TOKEN has 1 characters" in caplog.text


def test_an_admin_token_file_others_may_read_is_named_in_the_log(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    settings = make_settings(f"sqlite:///{tmp_path / 'srd.db'}", tmp_path, admin_token=None)
    settings.admin_token_file.write_text("srda_written-by-hand\n")
    settings.admin_token_file.chmod(0o644)
    with caplog.at_level(logging.WARNING), TestClient(create_app(settings)) as client:
        hand = {"Authorization": "Bearer srda_written-by-hand"}
        assert (
            client.post(
                "/jobs", json={"kind": "fish", "params": {"steps": 0}}, headers=hand
            ).status_code
            == 422
        )
    assert (
        f"the admin token file {settings.admin_token_file} may be read by others (mode 0644)"
        in caplog.text
    )


def test_settings_come_from_srd_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SRD_DATABASE_URL", "postgresql+psycopg://u@h/db")
    monkeypatch.setenv("SRD_MAX_BODY_BYTES", "4096")
    monkeypatch.setenv("SRD_ADMIN_TOKEN", "from-env")
    settings = Settings()
    assert settings.database_url == "postgresql+psycopg://u@h/db"
    assert settings.max_body_bytes == 4096
    assert settings.admin_token is not None
    assert settings.admin_token.get_secret_value() == "from-env"
    assert "from-env" not in repr(settings)


def test_a_job_memory_limit_no_worker_could_start_under_is_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A worker forked with torch loaded maps about 700 MB: under that limit every job failed
    before it began, the cause only in the server's log; under 1536 a default lavaland job."""
    for refused in ("700", "1024"):
        monkeypatch.setenv("SRD_JOB_MEMORY_MB", refused)
        with pytest.raises(ValidationError, match="job_memory_mb"):
            Settings()
    monkeypatch.setenv("SRD_JOB_MEMORY_MB", "1536")
    assert Settings().job_memory_mb == 1536


def test_a_sqlite_writer_waits_for_another_process_lock_and_then_writes(tmp_path: Path) -> None:
    """Another connection (as another process would) holds the write lock for a while: our
    write session waits for it, by polling, not failing, and writes once it is released."""
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    upgrade_schema(url)
    database = Database(url)
    other = sqlite3.connect(tmp_path / "srd.db", isolation_level=None, check_same_thread=False)
    other.execute("BEGIN IMMEDIATE")
    hold_s = 0.3
    release = threading.Timer(hold_s, other.execute, args=("COMMIT",))
    release.start()
    began = time.perf_counter()
    with database.session(write=True) as session:
        session.execute(text("PRAGMA user_version = 7"))  # any write
        session.commit()
    waited = time.perf_counter() - began
    release.join()
    other.close()
    with database.session(write=False) as session:
        assert session.execute(text("PRAGMA user_version")).scalar() == 7
        # the busy timeout is restored for every later statement on the connection
        assert session.execute(text("PRAGMA busy_timeout")).scalar() == SQLITE_BUSY_TIMEOUT_MS
    database.close()
    assert hold_s * 0.9 <= waited < hold_s + 5, waited


def test_a_sqlite_writer_gives_up_after_the_busy_timeout_an_outage_of_writes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    url = f"sqlite:///{tmp_path / 'srd.db'}"
    upgrade_schema(url)
    monkeypatch.setattr(db_module, "SQLITE_BUSY_TIMEOUT_MS", 200)
    database = Database(url)
    other = sqlite3.connect(tmp_path / "srd.db", isolation_level=None)
    other.execute("BEGIN IMMEDIATE")
    try:
        busy = pytest.raises(OperationalError, match="locked")
        with busy as raised, database.session(write=True) as s:
            s.execute(text("PRAGMA user_version = 8"))
        # writes stalled for the whole busy timeout are an outage of writes: the runners'
        # grace starts, and the outage began that long ago at the latest
        gave_up = datetime.now(UTC)
        database.note_outage(raised.value)
        assert database.since_outage_s() < 1
        began = database.outage_began()
        assert began is not None and began <= gave_up - timedelta(seconds=0.2)
    finally:
        other.execute("ROLLBACK")
        other.close()
        database.close()


def test_only_a_database_out_of_reach_starts_the_grace_of_an_outage(
    fresh_database_url: str,
) -> None:
    """A statement the database cancelled (PostgreSQL's statement timeout; SQLite's interrupt)
    says the database answered: it is not recorded as an outage. A server that cannot be
    reached is."""
    upgrade_schema(fresh_database_url)
    database = Database(fresh_database_url)
    try:
        with pytest.raises(OperationalError) as raised, database.session(write=False) as s:
            if fresh_database_url.startswith("postgresql"):
                s.execute(text("SET LOCAL statement_timeout = 20"))
                s.execute(text("SELECT pg_sleep(2)"))
            else:
                connection = s.connection().connection.driver_connection
                assert isinstance(connection, sqlite3.Connection)
                threading.Timer(0.05, connection.interrupt).start()
                s.execute(text(_SLOW_SQLITE_QUERY))
        database.note_outage(raised.value)
        assert database.since_outage_s() == math.inf, raised.value
        gone = (
            "postgresql+psycopg://nobody@127.0.0.1:1/none"
            if "postgresql" in fresh_database_url
            else "sqlite:////nonexistent-folder/srd.db"
        )
        with pytest.raises(OperationalError) as unreachable, create_engine(gone).connect() as c:
            c.execute(text("SELECT 1"))
        database.note_outage(unreachable.value)
        assert database.since_outage_s() < 5
    finally:
        database.close()


_SLOW_SQLITE_QUERY = (
    "WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM n WHERE i < 100000000) "
    "SELECT count(*) FROM n"
)


def test_json_columns_store_pre_encoded_json_as_it_is() -> None:
    """A manifest's ``model_dump_json`` goes into a JSON column unchanged (``JSONText``); any
    other value, a plain string included, is encoded."""
    from server.store.db import JSONText, json_dumps

    assert json_dumps(JSONText('{"a":[1.5,2]}')) == '{"a":[1.5,2]}'
    assert json_dumps('{"a":1}') == '"{\\"a\\":1}"'
    assert json_dumps({"a": [1.5, 2]}) == '{"a": [1.5, 2]}'


@pytest.mark.postgres
@pytest.mark.parametrize(
    ("given", "search_path"),
    [("", '"$user", public'), ("-c search_path=pg_catalog,public", "pg_catalog,public")],
)
def test_postgres_sessions_end_when_left_idle_in_a_transaction(
    given: str, search_path: str
) -> None:
    """A session of ours left in an open transaction (its client cut off without a word, the
    connection half-open) is ended by PostgreSQL after a minute, and so are its row locks: the
    server's own TCP keepalive would take two hours. A URL's own ``options`` are kept."""
    for url in postgres_database():
        database = Database(url + (f"?options={quote(given)}" if given else ""))
        try:
            with database.session(write=True) as session:
                shown = session.execute(text("SHOW idle_in_transaction_session_timeout"))
                assert shown.scalar_one() == "1min"
                assert session.execute(text("SHOW search_path")).scalar_one() == search_path
        finally:
            database.close()


def test_serve_logs_the_migration_it_runs(tmp_path: Path) -> None:
    """``srd serve`` on a database of an older release migrates it at start and says so in its
    log (the operator's record of the upgrade), from which revision to which."""
    from alembic import command

    from server.cli.launch import ServerProcess

    url = f"sqlite:///{tmp_path / 'srd.db'}"
    scripts = ScriptDirectory.from_config(alembic_config(url))
    head = scripts.get_current_head()
    assert head is not None
    before = scripts.get_revision(head).down_revision
    assert isinstance(before, str)
    command.upgrade(alembic_config(url), before)
    server = ServerProcess(database_url=url, data_dir=tmp_path / "data", admin_token=ADMIN_TOKEN)
    with server:
        pass
    logged = server.log_path.read_text()
    assert f"migrating the database {url} from {before} to {head}" in logged, logged
    assert "Running upgrade" not in logged  # one line of ours, not Alembic's docstrings


@pytest.mark.postgres
def test_a_server_whose_database_a_newer_release_migrates_takes_no_more_work(
    tmp_path: Path,
) -> None:
    """An old replica left running while a newer release's server migrates the PostgreSQL
    database: within seconds it says so in ``/healthz`` (not ready), answers every request
    with the JSON 503 naming the revision, and claims no auction (one created before the
    migration it played); a revision put back does not bring it back (stop it)."""
    for url in postgres_database():
        _an_old_replica_through_a_migration(url, tmp_path)


def _an_old_replica_through_a_migration(url: str, data_dir: Path) -> None:
    from sqlalchemy import select

    from server.cli.launch import ServerProcess
    from server.store import crud
    from server.store.tables import Auction
    from tests.support.live import submit_population

    engine = create_engine(url)

    def status(auction_id: int) -> tuple[str, str | None]:
        with engine.connect() as connection:
            query = select(Auction.status, Auction.lease_owner).where(Auction.id == auction_id)
            status, owner = connection.execute(query).one()
        return status, owner

    def created_elsewhere(model_ids: list[int]) -> int:
        """An auction as another replica's ``POST /auctions`` writes it."""
        database = Database(url)
        try:
            with database.session(write=True) as session:
                auction = crud.create_auction(
                    session, model_ids=model_ids, n_fish=1, rarity=None, max_iterations=64,
                    fine_tune=False, seed=0, opening_price=5.0,
                )  # fmt: skip
                session.commit()
                return auction.id
        finally:
            database.close()

    with ServerProcess(
        database_url=url, data_dir=data_dir, admin_token=ADMIN_TOKEN
    ) as server, httpx.Client(base_url=server.url, timeout=30) as client:  # fmt: skip
        answers = submit_population(client)
        ids = [a["model_id"] for name, a in answers.items() if name.startswith("honest")]
        before = created_elsewhere(ids)
        wait_for(lambda: {"status": status(before)[0]}, lambda s: s["status"] == "finished", 60)
        head = ScriptDirectory.from_config(alembic_config(url)).get_current_head()
        with engine.begin() as connection:
            connection.execute(text("UPDATE alembic_version SET version_num = '9999_newer'"))
        after = created_elsewhere(ids)
        health = wait_for(
            lambda: {"code": (r := client.get("/healthz")).status_code, **r.json()},
            lambda state: state["code"] == 503,
            timeout_s=15,
        )
        assert [p["check"] for p in health["problems"]] == ["database"], health
        assert "revision 9999_newer" in health["problems"][0]["msg"], health
        refused = client.post("/auctions", json={"n_fish": 1}, headers=ADMIN)
        assert refused.status_code == 503 and "Retry-After" in refused.headers
        detail = refused.json()["detail"][0]
        assert detail["loc"] == ["database"] and "newer release" in detail["msg"], detail
        time.sleep(3)  # more than a runner's idle pass
        assert status(after) == ("pending", None)
        with engine.begin() as connection:
            connection.execute(text(f"UPDATE alembic_version SET version_num = '{head}'"))
        time.sleep(1.5)  # more than a check's life
        assert client.get("/healthz").status_code == 503  # for good: stop it
    engine.dispose()
