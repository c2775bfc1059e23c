"""The job store: sessions, uploaded logs, streamed chunks and jobs, in SQLite (the default: one
file in WAL mode) or PostgreSQL (``LIDARMAP_DATABASE_URL=postgresql://...``, for several hosts).

Both backends run the same SQL through one :class:`JobStore`; a backend only opens a transaction
on a connection and says its placeholder style (queries are written with ``?``). The API
process and every worker process open the store; each operation is one transaction. SQLite opens a
short-lived connection per transaction; PostgreSQL borrows one from a per-process connection pool
(psycopg_pool, created on first use in each process, never pickled), so no connection crosses a
process and each is used by one thread at a time. Times are Unix seconds (float, stored as DOUBLE
PRECISION).

Atomicity: SQLite's ``BEGIN IMMEDIATE`` runs transactions one after another. PostgreSQL runs them
concurrently (READ COMMITTED), so every check-then-write is one conditional statement (the
queued -> running claim is ``UPDATE ... WHERE status = 'queued'``: a concurrent claimer waits for
the row lock, re-reads the row and updates nothing) and chunk inserts use ``ON CONFLICT``.
Checks that span rows of a session (a chunk beyond the stream's end, one live job per session)
first lock the session's row with a no-op ``UPDATE`` (:func:`_lock_session`), so those
transactions run one after another on both backends.
"""

from __future__ import annotations

import os
import re
import sqlite3
import threading
import time
import uuid
import zlib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import unquote

from api_schemas.jobs import JobSource, JobStatus
from service.http_errors import Unavailable
from service.storage.rows import (
    ACTIVE_STATUSES,
    TERMINAL_STATUSES,
    ChunkRow,
    JobRow,
    LogRow,
    SessionRow,
    StreamFigures,
    dump_json,
)

# SQL parameters are plain strings (a driver may adapt an Enum by its name)
_QUEUED, _RUNNING, _FAILED, _CANCELLED = (s.value for s in (JobStatus.QUEUED, JobStatus.RUNNING, JobStatus.FAILED,
                                                             JobStatus.CANCELLED))
POSTGRES_CONNECT_TIMEOUT_S = 10
POSTGRES_POOL_MAX_CONNECTIONS = 10  # per process: the API's request threads share them, a worker uses one
POSTGRES_QUICK_BORROW_S = 1.0  # a pooled connection not lent within this long: check the server directly

# Portable DDL: SQLite gives DOUBLE PRECISION and BIGINT columns REAL (8-byte float) and INTEGER
# (8-byte) affinity; PostgreSQL's REAL would be a 4-byte float (timestamps off by minutes).
# logs.upload_no numbers a session's uploads 1, 2, ... ("newest" must not depend on clock ties).
SCHEMA = """
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
SCHEMA_STATEMENTS = [s.strip() for s in SCHEMA.split(";") if s.strip()]


class StoreUnavailable(Unavailable):
    """The database cannot be reached (503); the message never contains a password."""


def new_id() -> str:
    """A random UUID4 string: every id the service hands out."""
    return str(uuid.uuid4())


@dataclass(frozen=True)
class ChunkOutcome:
    row: ChunkRow | None
    duplicate: bool
    conflict: bool
    beyond_end: int | None = None  # the stream was finished at this seq, below the chunk's: nothing stored


@dataclass(frozen=True)
class FinishOutcome:
    last_seq: int | None  # the stream's end now (None: nothing to finish, no chunk and no last_seq)
    conflict: str | None = None  # why the end could not be set (nothing was changed)


# ---- backends -----------------------------------------------------------------------------------


class SqliteBackend:
    """One SQLite file in WAL mode, on a disk of this host (its locking is unsafe on network file
    systems). ``BEGIN IMMEDIATE`` makes every transaction take the write lock at once."""

    placeholder = "?"

    def __init__(self, path: Path):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"SqliteBackend({str(self.path)!r})"

    @property
    def errors(self) -> tuple[type[Exception], ...]:
        return (sqlite3.Error,)

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        conn = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        conn.row_factory = _dict_row
        try:
            conn.execute("PRAGMA busy_timeout = 30000")
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")
        finally:
            conn.close()

    def create_schema(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        conn = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        try:
            conn.execute("PRAGMA journal_mode = WAL")
            for statement in SCHEMA_STATEMENTS:
                conn.execute(statement)
            if "upload_no" not in {row[1] for row in conn.execute("PRAGMA table_info(logs)")}:
                conn.execute("ALTER TABLE logs ADD COLUMN upload_no BIGINT NOT NULL DEFAULT 0")  # older files
        finally:
            conn.close()


class PostgresBackend:
    """A PostgreSQL database (psycopg 3) that the API and the workers of every host reach."""

    placeholder = "%s"
    _SCHEMA_LOCK = zlib.crc32(b"lidarmap job store schema")  # serialises concurrent schema creation

    def __init__(self, url: str):
        self.url = url
        self._pool: Any = None
        self._pool_pid: int | None = None
        self._pool_lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:
        return {"url": self.url}  # a worker process builds its own pool

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["url"])  # type: ignore[misc]

    def __repr__(self) -> str:
        return f"PostgresBackend({safe_url(self.url)!r})"

    def _connections(self) -> Any:
        """This process's connection pool (a forked child makes a new one; the parent's sockets are not its)."""
        with self._pool_lock:
            if self._pool is None or self._pool_pid != os.getpid():
                from psycopg.rows import dict_row
                from psycopg_pool import ConnectionPool

                self._pool = ConnectionPool(
                    self.url, min_size=1, max_size=POSTGRES_POOL_MAX_CONNECTIONS, open=False,
                    timeout=POSTGRES_CONNECT_TIMEOUT_S, name="lidarmap", check=ConnectionPool.check_connection,
                    kwargs={"row_factory": dict_row, "connect_timeout": POSTGRES_CONNECT_TIMEOUT_S,
                            "application_name": "lidarmap"})
                self._pool.open(wait=False)
                self._pool_pid = os.getpid()
            return self._pool

    def close(self) -> None:
        """Close this process's pool (its connections); the next transaction opens a new one."""
        with self._pool_lock:
            if self._pool is not None and self._pool_pid == os.getpid():
                self._pool.close()
            self._pool, self._pool_pid = None, None

    @property
    def errors(self) -> tuple[type[Exception], ...]:
        return (_psycopg().Error, StoreUnavailable)

    @contextmanager
    def transaction(self) -> Iterator[Any]:
        psycopg = _psycopg()
        from psycopg_pool import PoolTimeout

        pool = self._connections()
        try:
            conn = pool.getconn(timeout=POSTGRES_QUICK_BORROW_S)
        except PoolTimeout:
            conn = self._borrow_after_a_check(pool)
        try:
            with conn:  # commits when the block succeeds, rolls back when it raises (a pooled one stays open)
                yield conn
        except psycopg.OperationalError as exc:  # the server went away mid-transaction
            raise self._unavailable(exc) from None
        finally:
            pool.putconn(conn)  # checked before it is lent again: one the server dropped is replaced

    def _borrow_after_a_check(self, pool: Any) -> Any:
        """No pooled connection at once: when a direct connection fails too (server down, wrong
        password) say why at once; otherwise every connection is busy, so wait longer for one."""
        psycopg = _psycopg()
        from psycopg_pool import PoolTimeout

        try:
            psycopg.connect(self.url, connect_timeout=POSTGRES_CONNECT_TIMEOUT_S).close()
        except psycopg.Error as exc:
            raise self._unavailable(exc) from None
        try:
            return pool.getconn(timeout=POSTGRES_CONNECT_TIMEOUT_S)
        except PoolTimeout:
            raise self._unavailable(RuntimeError(
                f"all {POSTGRES_POOL_MAX_CONNECTIONS} pooled connections stayed busy for "
                f"{POSTGRES_CONNECT_TIMEOUT_S} s")) from None

    def create_schema(self) -> None:
        with self.transaction() as conn:
            conn.execute("SELECT pg_advisory_xact_lock(%s)", (self._SCHEMA_LOCK,))
            for statement in SCHEMA_STATEMENTS:
                conn.execute(statement)

    def _unavailable(self, exc: Exception) -> StoreUnavailable:
        reason = str(exc).strip()
        for secret in _url_secrets(self.url):
            reason = reason.replace(secret, "***")
        return StoreUnavailable(f"the job store at {safe_url(self.url)} is unavailable: {reason}")


def _psycopg() -> Any:
    try:
        import psycopg
    except ImportError as exc:
        raise RuntimeError("LIDARMAP_DATABASE_URL names PostgreSQL but psycopg is not installed: "
                           "pip install 'lidarmap[distributed]'") from exc
    return psycopg


def _dict_row(cursor: sqlite3.Cursor, row: tuple) -> dict[str, Any]:
    return {column[0]: value for column, value in zip(cursor.description, row, strict=True)}


class _Transaction:
    """An open transaction that takes ``?`` placeholders whatever the backend."""

    def __init__(self, conn: Any, placeholder: str):
        self._conn, self._placeholder = conn, placeholder

    def execute(self, sql: str, params: Sequence[Any] = ()) -> Any:
        if self._placeholder != "?":
            sql = sql.replace("?", self._placeholder)
        return self._conn.execute(sql, tuple(params)) if params else self._conn.execute(sql)


Backend = SqliteBackend | PostgresBackend


class JobStore:
    """The service's persistence; every method is one transaction. ``JobStore(path)`` is SQLite
    at ``path``; pass a :class:`PostgresBackend` for PostgreSQL (or use :func:`open_store`)."""

    def __init__(self, backend: Backend | Path):
        self.backend = backend if isinstance(backend, SqliteBackend | PostgresBackend) else SqliteBackend(backend)

    def __repr__(self) -> str:
        return f"JobStore({self.backend!r})"

    def close(self) -> None:
        """Close pooled connections (PostgreSQL); SQLite holds none between transactions."""
        if isinstance(self.backend, PostgresBackend):
            self.backend.close()

    @contextmanager
    def _tx(self) -> Iterator[_Transaction]:
        with self.backend.transaction() as conn:
            yield _Transaction(conn, self.backend.placeholder)

    def initialise(self) -> None:
        """Create the tables (idempotent; SQLite: the file too, in WAL mode)."""
        self.backend.create_schema()

    def ping(self) -> bool:
        """True when the database answers a query."""
        try:
            with self._tx() as tx:
                tx.execute("SELECT count(*) AS n FROM jobs").fetchone()
            return True
        except self.backend.errors:
            return False

    # ---- sessions -------------------------------------------------------------------------------

    def create_session(self, owner: str, name: str, vehicle_preset: str | None,
                       calibration: dict[str, Any] | None, geo: dict[str, Any] | None) -> SessionRow:
        session_id = new_id()
        with self._tx() as tx:
            tx.execute("INSERT INTO sessions (id, owner, name, vehicle_preset, calibration_json, geo_json, "
                       "created_at) VALUES (?, ?, ?, ?, ?, ?, ?)",
                       (session_id, owner, name, vehicle_preset, dump_json(calibration), dump_json(geo), time.time()))
            row = tx.execute(_SESSION_SELECT + " WHERE s.id = ?", (session_id,)).fetchone()
        return SessionRow.from_db(row)

    def get_session(self, session_id: str, owner: str) -> SessionRow | None:
        with self._tx() as tx:
            row = tx.execute(_SESSION_SELECT + " WHERE s.id = ? AND s.owner = ?", (session_id, owner)).fetchone()
        return None if row is None else SessionRow.from_db(row)

    def list_sessions(self, owner: str, limit: int, offset: int) -> tuple[list[SessionRow], int]:
        with self._tx() as tx:
            rows = tx.execute(_SESSION_SELECT + " WHERE s.owner = ? ORDER BY s.created_at DESC LIMIT ? OFFSET ?",
                              (owner, limit, offset)).fetchall()
            count = tx.execute("SELECT count(*) AS n FROM sessions WHERE owner = ?", (owner,)).fetchone()["n"]
        return [SessionRow.from_db(r) for r in rows], int(count)

    def delete_session(self, session_id: str) -> list[str]:
        """Delete the session with its logs, chunks and jobs; returns the deleted job ids."""
        with self._tx() as tx:
            job_ids = [r["id"] for r in tx.execute("SELECT id FROM jobs WHERE session_id = ?", (session_id,))]
            for table in ("logs", "chunks", "jobs", "stream_ends"):
                tx.execute(f"DELETE FROM {table} WHERE session_id = ?", (session_id,))
            tx.execute("DELETE FROM sessions WHERE id = ?", (session_id,))
        return job_ids

    # ---- logs -----------------------------------------------------------------------------------

    def add_log(self, log_id: str, session_id: str, filename: str, size_bytes: int, sha256: str,
                archive: bool, summary: dict[str, Any], stored_path: str) -> LogRow | None:
        """``stored_path``: where the log lies, relative to the data folder (built from ids only).
        None (nothing stored) when the session no longer exists."""
        row = {"id": log_id, "session_id": session_id, "filename": filename, "size_bytes": size_bytes,
               "sha256": sha256, "archive": int(archive), "format": summary.get("format", "unknown"),
               "summary_json": dump_json(summary), "stored_path": stored_path, "created_at": time.time()}
        with self._tx() as tx:
            _lock_session(tx, session_id)
            if tx.execute("SELECT 1 AS one FROM sessions WHERE id = ?", (session_id,)).fetchone() is None:
                return None  # the session was deleted while the log arrived
            tx.execute(f"INSERT INTO logs ({', '.join(row)}, upload_no) VALUES ({', '.join('?' * len(row))}, "
                       "(SELECT coalesce(max(upload_no), 0) + 1 FROM logs WHERE session_id = ?))",
                       (*row.values(), session_id))
        return LogRow.from_db(row)

    def stored_ids(self) -> dict[str, set[str]]:
        """Every session, log and job id in the store (to find files that nothing refers to)."""
        with self._tx() as tx:
            return {table: {r["id"] for r in tx.execute(f"SELECT id FROM {table}").fetchall()}
                    for table in ("sessions", "logs", "jobs")}

    def get_log(self, log_id: str, session_id: str) -> LogRow | None:
        with self._tx() as tx:
            row = tx.execute("SELECT * FROM logs WHERE id = ? AND session_id = ?", (log_id, session_id)).fetchone()
        return None if row is None else LogRow.from_db(row)

    def list_logs(self, session_id: str) -> list[LogRow]:
        """Logs of a session, newest first."""
        with self._tx() as tx:
            rows = tx.execute("SELECT * FROM logs WHERE session_id = ? ORDER BY upload_no DESC, created_at DESC",
                              (session_id,)).fetchall()
        return [LogRow.from_db(r) for r in rows]

    # ---- chunks ---------------------------------------------------------------------------------

    def put_chunk(self, session_id: str, seq: int, sha256: str, messages: int,
                  t_first_s: float, t_last_s: float) -> ChunkOutcome:
        """Record chunk ``seq`` once: a retry with the same hash is a duplicate, another hash a conflict;
        a new chunk beyond the end of a finished stream is refused (``beyond_end``)."""
        row = {"session_id": session_id, "seq": seq, "sha256": sha256, "messages": messages,
               "t_first_s": t_first_s, "t_last_s": t_last_s, "created_at": time.time()}
        with self._tx() as tx:
            _lock_session(tx, session_id)
            end = _stream_end(tx, session_id)
            if end is not None and seq > end:
                return ChunkOutcome(None, duplicate=False, conflict=False, beyond_end=end)
            inserted = tx.execute(f"INSERT INTO chunks ({', '.join(row)}) VALUES ({', '.join('?' * len(row))}) "
                                  "ON CONFLICT (session_id, seq) DO NOTHING", tuple(row.values())).rowcount
            if inserted == 1:
                return ChunkOutcome(ChunkRow.from_db(row), duplicate=False, conflict=False)
            old = tx.execute("SELECT * FROM chunks WHERE session_id = ? AND seq = ?", (session_id, seq)).fetchone()
        return ChunkOutcome(ChunkRow.from_db(old), duplicate=old["sha256"] == sha256, conflict=old["sha256"] != sha256)

    def finish_stream(self, session_id: str, last_seq: int | None) -> FinishOutcome:
        """Declare the stream's last seq (default: the highest received). Idempotent for the same end;
        refused (``conflict``) for another end than the one set, or below a chunk already received."""
        with self._tx() as tx:
            _lock_session(tx, session_id)
            highest = tx.execute("SELECT max(seq) AS highest FROM chunks WHERE session_id = ?",
                                 (session_id,)).fetchone()["highest"]
            end = _stream_end(tx, session_id)
            wanted = last_seq if last_seq is not None else (end if end is not None else highest)
            if wanted is None:
                return FinishOutcome(None, "the stream has no chunks: send some, or give 'last_seq'")
            wanted = int(wanted)
            if end is not None:
                if end != wanted:
                    return FinishOutcome(end, f"the stream was already finished at seq {end}")
                return FinishOutcome(end)
            if highest is not None and int(highest) > wanted:
                return FinishOutcome(None, f"chunk {int(highest)} was already received, beyond last_seq {wanted}")
            tx.execute("INSERT INTO stream_ends (session_id, last_seq, finished_at) VALUES (?, ?, ?)",
                       (session_id, wanted, time.time()))
        return FinishOutcome(wanted)

    def stream_end(self, session_id: str) -> int | None:
        """The finished stream's last seq; None while the stream is open."""
        with self._tx() as tx:
            return _stream_end(tx, session_id)

    def delete_chunk(self, session_id: str, seq: int) -> None:
        """Forget chunk ``seq`` (its file could not be written)."""
        with self._tx() as conn:
            conn.execute("DELETE FROM chunks WHERE session_id = ? AND seq = ?", (session_id, seq))

    def chunk_rows_near(self, session_id: str, seq: int) -> list[ChunkRow]:
        """Chunks seq-1, seq and seq+1 (what a new chunk is checked against), without reading the rest."""
        with self._tx() as conn:
            rows = conn.execute("SELECT * FROM chunks WHERE session_id = ? AND seq BETWEEN ? AND ? ORDER BY seq",
                                (session_id, seq - 1, seq + 1)).fetchall()
        return [ChunkRow.from_db(r) for r in rows]

    def stream_figures(self, session_id: str, max_after: int = 5000) -> StreamFigures:
        """The stream's state computed in SQL (cheap for long streams): chunks received, the end of
        the contiguous run from seq 0 (-1: none), the messages in it, the highest seq, the seqs
        received beyond the run (at most ``max_after``, ascending) and the stream's declared last
        seq (None while open)."""
        with self._tx() as conn:
            totals = conn.execute("SELECT count(*) AS received, max(seq) AS highest FROM chunks "
                                  "WHERE session_id = ?", (session_id,)).fetchone()
            received, highest = totals["received"], totals["highest"]
            k = conn.execute(
                "SELECT CASE WHEN EXISTS (SELECT 1 FROM chunks WHERE session_id = ? AND seq = 0) THEN "
                "(SELECT min(c.seq) FROM chunks c WHERE c.session_id = ? AND NOT EXISTS "
                "(SELECT 1 FROM chunks d WHERE d.session_id = ? AND d.seq = c.seq + 1)) ELSE -1 END AS k",
                (session_id, session_id, session_id)).fetchone()["k"]
            messages = conn.execute("SELECT coalesce(sum(messages), 0) AS n FROM chunks WHERE session_id = ? "
                                    "AND seq <= ?", (session_id, k)).fetchone()["n"]
            after = [r["seq"] for r in conn.execute("SELECT seq FROM chunks WHERE session_id = ? AND seq > ? "
                                                    "ORDER BY seq LIMIT ?", (session_id, k, max_after))]
            end = _stream_end(conn, session_id)
        return StreamFigures(received=int(received), contiguous_through=int(k), messages=int(messages),
                             highest=-1 if highest is None else int(highest), after=[int(s) for s in after],
                             last_seq=end)

    def chunk_rows(self, session_id: str) -> list[ChunkRow]:
        """All chunks of a session in seq order."""
        with self._tx() as tx:
            rows = tx.execute("SELECT * FROM chunks WHERE session_id = ? ORDER BY seq", (session_id,)).fetchall()
        return [ChunkRow.from_db(r) for r in rows]

    # ---- jobs -----------------------------------------------------------------------------------

    def create_job(self, session_id: str, owner: str, source: JobSource, log_id: str | None,
                   config: dict[str, Any]) -> JobRow:
        """A new queued job."""
        job_id = new_id()
        with self._tx() as tx:
            _insert_job(tx, job_id, session_id, owner, JobSource(source), log_id, config)
            return _job_row(tx, job_id)

    def create_live_job(self, session_id: str, owner: str,
                        config: dict[str, Any]) -> tuple[JobRow | None, JobRow | None]:
        """A live stream job, unless the session has one queued or running: (new row, None) or
        (None, the active live job's row)."""
        job_id = new_id()
        with self._tx() as tx:
            _lock_session(tx, session_id)
            active = tx.execute(f"SELECT * FROM jobs WHERE session_id = ? AND status IN {_ACTIVE} "
                                "ORDER BY created_at", (session_id, *_ACTIVE_VALUES)).fetchall()
            for row in map(JobRow.from_db, active):
                if row.live:
                    return None, row
            _insert_job(tx, job_id, session_id, owner, JobSource.STREAM, None, config)
            return _job_row(tx, job_id), None

    def get_job(self, job_id: str, owner: str | None = None) -> JobRow | None:
        """The job, or None when unknown (or owned by someone else when ``owner`` is given)."""
        with self._tx() as tx:
            row = tx.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None or (owner is not None and row["owner"] != owner):
            return None
        return JobRow.from_db(row)

    def list_jobs(self, owner: str, session_id: str | None, status: JobStatus | None,
                  limit: int, offset: int) -> tuple[list[JobRow], int]:
        where, args = ["owner = ?"], [owner]
        if session_id is not None:
            where.append("session_id = ?")
            args.append(session_id)
        if status is not None:
            where.append("status = ?")
            args.append(JobStatus(status).value)
        clause = " AND ".join(where)
        with self._tx() as tx:
            rows = tx.execute(f"SELECT * FROM jobs WHERE {clause} ORDER BY created_at DESC LIMIT ? OFFSET ?",
                              (*args, limit, offset)).fetchall()
            count = tx.execute(f"SELECT count(*) AS n FROM jobs WHERE {clause}", args).fetchone()["n"]
        return [JobRow.from_db(r) for r in rows], int(count)

    def jobs_with_status(self, *statuses: JobStatus) -> list[str]:
        """Ids of the jobs in any of ``statuses``, oldest first."""
        marks = ", ".join("?" * len(statuses))
        with self._tx() as tx:
            rows = tx.execute(f"SELECT id FROM jobs WHERE status IN ({marks}) ORDER BY created_at",
                              [JobStatus(s).value for s in statuses])
            return [r["id"] for r in rows]

    def mark_running(self, job_id: str, worker_pid: int) -> bool:
        """The claim, queued -> running in one conditional update; False when the job is no longer
        queued (another worker claimed it, or it was cancelled meanwhile)."""
        now = time.time()
        with self._tx() as tx:
            cur = tx.execute("UPDATE jobs SET status = ?, started_at = ?, heartbeat_at = ?, "
                             "worker_pid = ? WHERE id = ? AND status = ? AND cancel_requested = 0",
                             (_RUNNING, now, now, worker_pid, job_id, _QUEUED))
            return cur.rowcount == 1

    def set_input(self, job_id: str, input_description: dict[str, Any]) -> None:
        with self._tx() as tx:
            tx.execute("UPDATE jobs SET input_json = ? WHERE id = ?", (dump_json(input_description), job_id))

    def update_progress(self, job_id: str, scans_done: int, scans_total: int | None) -> bool:
        """Record progress and heartbeat; returns whether a cancel was requested."""
        progress = 0.0 if not scans_total else min(1.0, max(0.0, scans_done / scans_total))
        with self._tx() as tx:
            tx.execute("UPDATE jobs SET scans_done = ?, scans_total = ?, progress = ?, heartbeat_at = ? "
                       "WHERE id = ? AND status = ?",
                       (scans_done, scans_total, progress, time.time(), job_id, _RUNNING))
            row = tx.execute("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return row is None or bool(row["cancel_requested"])

    def cancel_requested(self, job_id: str) -> bool:
        with self._tx() as tx:
            row = tx.execute("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return row is None or bool(row["cancel_requested"])

    def set_products(self, job_id: str, products: dict[str, str]) -> None:
        """Product name -> file name inside the job's artifact folder."""
        with self._tx() as tx:
            tx.execute("UPDATE jobs SET products_json = ? WHERE id = ?", (dump_json(products), job_id))

    def finish(self, job_id: str, status: JobStatus, error: str | None = None) -> bool:
        """An active job -> a terminal status (first writer wins); False when already terminal."""
        status = JobStatus(status)
        if status not in TERMINAL_STATUSES:
            raise ValueError(f"a job finishes as one of {[s.value for s in TERMINAL_STATUSES]}, not {status.value!r}")
        with self._tx() as tx:
            extra = ", progress = 1.0" if status is JobStatus.SUCCEEDED else ""
            cur = tx.execute(f"UPDATE jobs SET status = ?, error = ?, finished_at = ?{extra} "
                             f"WHERE id = ? AND status IN {_ACTIVE}",
                             (status.value, error, time.time(), job_id, *_ACTIVE_VALUES))
            return cur.rowcount == 1

    def request_cancel(self, job_id: str) -> JobStatus | None:
        """Ask a job to stop: a queued job is cancelled at once, a running one is flagged for its
        worker. Returns the status afterwards (None: no such job)."""
        with self._tx() as tx:
            tx.execute(f"UPDATE jobs SET cancel_requested = 1 WHERE id = ? AND status IN {_ACTIVE}",
                       (job_id, *_ACTIVE_VALUES))
            tx.execute("UPDATE jobs SET status = ?, error = 'cancelled by request', finished_at = ? "
                       "WHERE id = ? AND status = ?", (_CANCELLED, time.time(), job_id, _QUEUED))
            row = tx.execute("SELECT status FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return None if row is None else JobStatus(row["status"])

    def heartbeat(self, job_id: str) -> bool:
        """A running job's worker is alive; returns whether the job should stop (cancel requested,
        or no longer running because it was failed meanwhile)."""
        with self._tx() as tx:
            tx.execute("UPDATE jobs SET heartbeat_at = ? WHERE id = ? AND status = ?",
                       (time.time(), job_id, _RUNNING))
            row = tx.execute("SELECT status, cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return row is None or row["status"] != JobStatus.RUNNING or bool(row["cancel_requested"])

    def fail_lost(self, silent_s: float) -> list[str]:
        """Running jobs whose heartbeat is older than ``silent_s`` -> failed 'worker lost' (their
        cancel flag is set too, so a worker that was only slow stops at its next progress report).
        Each update re-checks the heartbeat: one that arrives meanwhile keeps its job running."""
        now = time.time()
        silent = "status = ? AND coalesce(heartbeat_at, started_at, 0) < ?"
        failed = []
        with self._tx() as tx:
            rows = tx.execute(f"SELECT id, heartbeat_at, worker_pid FROM jobs WHERE {silent}",
                              (_RUNNING, now - silent_s)).fetchall()
            for row in rows:
                silence = f"{now - row['heartbeat_at']:.0f} s" if row["heartbeat_at"] else "ever"
                reason = (f"worker lost: no heartbeat for {silence} (worker pid {row['worker_pid']}): its process "
                          "or machine stopped")
                cur = tx.execute(f"UPDATE jobs SET status = ?, cancel_requested = 1, finished_at = ?, "
                                 f"error = ? WHERE id = ? AND {silent}",
                                 (_FAILED, now, reason, row["id"], _RUNNING, now - silent_s))
                if cur.rowcount == 1:
                    failed.append(row["id"])
        return failed

    def fail_interrupted(self) -> list[str]:
        """At start-up: jobs left 'running' by a previous process cannot resume -> failed 'interrupted'."""
        with self._tx() as tx:
            rows = tx.execute("UPDATE jobs SET status = ?, finished_at = ?, error = 'interrupted: the "
                              "service stopped while the job was running' WHERE status = ? RETURNING id",
                              (_FAILED, time.time(), _RUNNING)).fetchall()
        return [r["id"] for r in rows]


def _lock_session(tx: _Transaction, session_id: str) -> None:
    """Hold the session's row lock until the transaction ends (PostgreSQL; SQLite's BEGIN IMMEDIATE
    already serialises every transaction)."""
    tx.execute("UPDATE sessions SET id = id WHERE id = ?", (session_id,))


def _stream_end(tx: _Transaction, session_id: str) -> int | None:
    row = tx.execute("SELECT last_seq FROM stream_ends WHERE session_id = ?", (session_id,)).fetchone()
    return None if row is None else int(row["last_seq"])


_SESSION_SELECT = (
    "SELECT s.*, (SELECT count(*) FROM logs l WHERE l.session_id = s.id) AS n_logs, "
    "(SELECT count(*) FROM chunks c WHERE c.session_id = s.id) AS n_chunks, "
    "(SELECT count(*) FROM jobs j WHERE j.session_id = s.id) AS n_jobs FROM sessions s"
)


_ACTIVE_VALUES = tuple(status.value for status in ACTIVE_STATUSES)  # SQL parameters: plain strings
_ACTIVE = "(" + ", ".join("?" * len(_ACTIVE_VALUES)) + ")"  # their placeholders


def _insert_job(tx: _Transaction, job_id: str, session_id: str, owner: str, source: JobSource, log_id: str | None,
                config: dict[str, Any]) -> None:
    tx.execute("INSERT INTO jobs (id, session_id, owner, source, log_id, config_json, status, created_at) "
               "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
               (job_id, session_id, owner, source.value, log_id, dump_json(config), _QUEUED, time.time()))


def _job_row(tx: _Transaction, job_id: str) -> JobRow:
    return JobRow.from_db(tx.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone())


# ---- LIDARMAP_DATABASE_URL ----------------------------------------------------------------------


def open_store(database_url: str, default_path: Path) -> JobStore:
    """The job store that ``LIDARMAP_DATABASE_URL`` names: empty = SQLite at ``default_path``;
    ``sqlite:////abs/path.sqlite3`` (or ``sqlite:///relative/path``) = SQLite there;
    ``postgresql://user:password@host:5432/dbname`` (or ``postgres://``, with libpq's query
    parameters such as ``?sslmode=require``) = PostgreSQL."""
    if not database_url:
        return JobStore(default_path)
    scheme, sep, rest = database_url.partition("://")
    if sep and scheme == "sqlite" and rest.startswith("/") and len(rest) > 1:
        return JobStore(Path(rest[1:]))
    if sep and scheme in ("postgresql", "postgres") and rest:
        return JobStore(PostgresBackend(database_url))
    raise ValueError(f"unsupported LIDARMAP_DATABASE_URL {safe_url(database_url)!r}: use "
                     "postgresql://user:password@host:5432/dbname, sqlite:////absolute/path.sqlite3, "
                     "or leave it empty for SQLite in the data folder")


def safe_url(url: str) -> str:
    """``url`` for messages and logs: its password (``user:PASSWORD@host``, ``password=`` query
    parameter) replaced by ``***``."""
    scheme, sep, rest = url.partition("://")
    if sep and "@" in rest:
        credentials, _, host = rest.rpartition("@")
        user, has_password, _ = credentials.partition(":")
        if has_password:
            rest = f"{user}:***@{host}" if user else f"***@{host}"
    return re.sub(r"(?i)(password=)[^&]*", r"\1***", f"{scheme}{sep}{rest}")


def _url_secrets(url: str) -> list[str]:
    """The passwords in ``url``, as written and percent-decoded (to scrub them from driver messages)."""
    secrets = re.findall(r"(?i)password=([^&]+)", url)
    _, sep, rest = url.partition("://")
    if sep and "@" in rest:
        secrets.append(rest.rpartition("@")[0].partition(":")[2])
    secrets += [unquote(s) for s in secrets]
    return sorted({s for s in secrets if s}, key=len, reverse=True)
