"""The job store's schema is Alembic's: migrations run on SQLite and on a real PostgreSQL server
(``conftest.py``), give exactly the tables of ``service/storage/tables.py``, go down and up again,
adopt a database that the store made before migrations (its rows kept), and run once when several
processes start together."""

from __future__ import annotations

import pickle
import sqlite3
import threading
from collections.abc import Iterator

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from service_helpers import store_on_backend
from sqlalchemy import inspect, text

from api_schemas.jobs import JobSource, JobStatus
from service.storage.migration import alembic_config, compare_type, current_revision, head_revision
from service.storage.store import JobStore, PostgresBackend
from service.storage.tables import metadata

# The schema that the store created at every start before migrations (0.1.0), verbatim.
PRE_MIGRATION_SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY, owner TEXT NOT NULL, name TEXT NOT NULL, vehicle_preset TEXT,
    calibration_json TEXT, geo_json TEXT, created_at DOUBLE PRECISION NOT NULL);
CREATE TABLE IF NOT EXISTS logs (
    id TEXT PRIMARY KEY, session_id TEXT NOT NULL, filename TEXT NOT NULL, size_bytes BIGINT NOT NULL,
    sha256 TEXT NOT NULL, archive INTEGER NOT NULL, format TEXT NOT NULL, summary_json TEXT NOT NULL,
    stored_path TEXT NOT NULL, created_at DOUBLE PRECISION NOT NULL, upload_no BIGINT NOT NULL DEFAULT 0);
CREATE INDEX IF NOT EXISTS logs_session ON logs(session_id, created_at);
CREATE TABLE IF NOT EXISTS chunks (
    session_id TEXT NOT NULL, seq BIGINT NOT NULL, sha256 TEXT NOT NULL, messages BIGINT NOT NULL,
    t_first_s DOUBLE PRECISION NOT NULL, t_last_s DOUBLE PRECISION NOT NULL, created_at DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (session_id, seq));
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY, session_id TEXT NOT NULL, owner TEXT NOT NULL, source TEXT NOT NULL, log_id TEXT,
    config_json TEXT NOT NULL, status TEXT NOT NULL, progress DOUBLE PRECISION NOT NULL DEFAULT 0,
    scans_done BIGINT NOT NULL DEFAULT 0, scans_total BIGINT, error TEXT,
    cancel_requested INTEGER NOT NULL DEFAULT 0, input_json TEXT, products_json TEXT,
    worker_pid BIGINT, created_at DOUBLE PRECISION NOT NULL, started_at DOUBLE PRECISION,
    finished_at DOUBLE PRECISION, heartbeat_at DOUBLE PRECISION);
CREATE INDEX IF NOT EXISTS jobs_session ON jobs(session_id, created_at);
CREATE TABLE IF NOT EXISTS stream_ends (
    session_id TEXT PRIMARY KEY, last_seq BIGINT NOT NULL, finished_at DOUBLE PRECISION NOT NULL);
CREATE INDEX IF NOT EXISTS jobs_status ON jobs(status);
"""
TABLES = {"sessions", "logs", "chunks", "jobs", "stream_ends"}


@pytest.fixture(params=["sqlite", "postgres"])
def new_store(request, tmp_path) -> Iterator[JobStore]:
    """A store on an empty database (not initialised) on each backend."""
    store = store_on_backend(request, tmp_path)
    yield store
    store.close()


def schema_differences(store: JobStore) -> list:
    """What Alembic's autogenerate finds between the database and ``tables.py`` (types included)."""
    with store.backend.transaction() as conn:
        return compare_metadata(MigrationContext.configure(conn, opts={"compare_type": compare_type}), metadata)


def tables_and_indexes(store: JobStore) -> dict[str, list]:
    with store.backend.transaction() as conn:
        found = inspect(conn)
        return {t: sorted((i["name"], tuple(i["column_names"])) for i in found.get_indexes(t))
                for t in found.get_table_names()}


def revision(store: JobStore) -> str | None:
    with store.backend.transaction() as conn:
        return current_revision(conn)


def test_migrations_create_the_schema_of_the_tables(new_store) -> None:
    assert revision(new_store) is None
    new_store.initialise()
    assert revision(new_store) == head_revision() == "0001"
    assert schema_differences(new_store) == []
    assert tables_and_indexes(new_store) == {
        "alembic_version": [], "chunks": [], "sessions": [], "stream_ends": [],
        "logs": [("logs_session", ("session_id", "created_at"))],
        "jobs": [("jobs_session", ("session_id", "created_at")), ("jobs_status", ("status",))]}
    new_store.initialise()  # at head: nothing to do
    assert revision(new_store) == "0001" and schema_differences(new_store) == []


def test_migrations_go_down_and_up_again(new_store) -> None:
    new_store.initialise()
    with new_store.backend.transaction() as conn:
        command.downgrade(alembic_config(conn), "base")
    assert set(tables_and_indexes(new_store)) == {"alembic_version"} and revision(new_store) is None
    new_store.initialise()
    assert revision(new_store) == "0001" and schema_differences(new_store) == []
    sid = new_store.create_session("alice", "after a round trip", None, None, None).id
    assert new_store.get_session(sid, "alice").name == "after a round trip"


def test_a_database_made_before_migrations_is_migrated_with_its_rows(new_store) -> None:
    """The 0.1.0 schema, with a session, a log, a chunk and a running job in it: the service's start
    adopts it at the initial revision and every row stays readable."""
    with new_store.backend.transaction() as conn:
        for statement in filter(str.strip, PRE_MIGRATION_SCHEMA.split(";")):
            conn.execute(text(statement))
        conn.execute(text("INSERT INTO sessions VALUES ('s1', 'alice', 'old drive', NULL, NULL, NULL, 1.5e9)"))
        conn.execute(text("INSERT INTO logs VALUES ('l1', 's1', 'a.clf', 7, 'aa', 0, 'carmen', '{}', 'p', "
                          "1.5e9, 1)"))
        conn.execute(text("INSERT INTO chunks VALUES ('s1', 0, 'h0', 3, 0.0, 0.5, 1.5e9)"))
        conn.execute(text("INSERT INTO jobs (id, session_id, owner, source, config_json, status, created_at, "
                          "started_at) VALUES ('j1', 's1', 'alice', 'log', '{}', 'running', 1.5e9, 1.5e9)"))
    assert revision(new_store) is None and "alembic_version" not in tables_and_indexes(new_store)

    new_store.initialise()
    assert revision(new_store) == "0001"
    # SQLite let an inline TEXT PRIMARY KEY hold NULL (a quirk kept for old files); the migration
    # leaves those four tables as they are rather than copy them: no other difference
    expected = [] if isinstance(new_store.backend, PostgresBackend) else [
        ("jobs", "id"), ("logs", "id"), ("sessions", "id"), ("stream_ends", "session_id")]
    assert sorted((d[0][2], d[0][3]) for d in schema_differences(new_store)
                  if d[0][0] == "modify_nullable" and d[0][5] is True) == expected
    assert len(schema_differences(new_store)) == len(expected)
    session = new_store.get_session("s1", "alice")
    assert (session.name, session.logs, session.chunks, session.jobs) == ("old drive", 1, 1, 1)
    assert [log.id for log in new_store.list_logs("s1")] == ["l1"]
    assert new_store.fail_interrupted() == ["j1"]
    new_store.add_log("l2", "s1", "b.clf", 1, "bb", False, {}, "q")
    assert [log.id for log in new_store.list_logs("s1")] == ["l2", "l1"]  # numbered after the old one


def test_a_sqlite_file_from_before_upload_numbers_is_migrated(tmp_path) -> None:
    """An older SQLite file: a logs table without upload_no, nothing else."""
    path = tmp_path / "old.sqlite3"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE logs (id TEXT PRIMARY KEY, session_id TEXT NOT NULL, filename TEXT NOT NULL, "
                     "size_bytes INTEGER NOT NULL, sha256 TEXT NOT NULL, archive INTEGER NOT NULL, format TEXT "
                     "NOT NULL, summary_json TEXT NOT NULL, stored_path TEXT NOT NULL, created_at REAL NOT NULL)")
    conn.close()
    store = JobStore(path)
    store.initialise()
    assert revision(store) == "0001"
    assert set(tables_and_indexes(store)) == TABLES | {"alembic_version"}
    assert "upload_no" in {c["name"] for c in inspect_columns(store, "logs")}
    assert tables_and_indexes(store)["logs"] == [("logs_session", ("session_id", "created_at"))]


def inspect_columns(store: JobStore, table: str) -> list[dict]:
    with store.backend.transaction() as conn:
        return inspect(conn).get_columns(table)


def test_a_new_sqlite_database_waits_for_a_writer_before_its_journal_mode(tmp_path) -> None:
    """SQLite refuses the switch to WAL at once ("database is locked"), without its busy timeout, while
    another process writes: a store starting then waits for it (2 starts of 60 failed with six stores
    starting together on a new file)."""
    from service.storage.database import SqliteBackend

    path = tmp_path / "lidarmap.sqlite3"
    writer = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    writer.execute("CREATE TABLE other (x INTEGER)")
    writer.execute("BEGIN IMMEDIATE")
    writer.execute("INSERT INTO other VALUES (1)")
    release = threading.Timer(0.3, lambda: writer.execute("COMMIT"))
    release.start()
    store = JobStore(SqliteBackend(path))
    try:
        store.initialise()  # switches to WAL once the writer is done, then migrates
    finally:
        release.join()
        writer.close()
    assert revision(store) == head_revision()
    with sqlite3.connect(path) as conn:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    store.close()


def test_processes_starting_together_migrate_once(new_store) -> None:
    """Four stores (as the API and three workers) initialise one new database at the same instant."""
    stores = [pickle.loads(pickle.dumps(new_store)) for _ in range(4)]  # as sent to worker processes
    barrier, errors = threading.Barrier(len(stores)), []

    def start(store: JobStore) -> None:
        try:
            barrier.wait(timeout=30)
            store.initialise()
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=start, args=(store,)) for store in stores]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    for store in stores:
        store.close()
    assert errors == []
    with new_store.backend.transaction() as conn:
        assert conn.execute(text("SELECT version_num FROM alembic_version")).scalars().all() == ["0001"]
    sid = new_store.create_session("", "s", None, None, None).id
    job = new_store.create_job(sid, "", JobSource.LOG, None, {})
    assert new_store.get_job(job.id).status is JobStatus.QUEUED
