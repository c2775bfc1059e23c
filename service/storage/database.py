"""The job store's database: the schema, the two backends (SQLite, the default: one file in WAL
mode; PostgreSQL, ``LIDARMAP_DATABASE_URL=postgresql://...``, for several hosts), the transaction
that every operation of the store runs in (:class:`StoreBase`), and ``LIDARMAP_DATABASE_URL`` made
safe for messages (:func:`safe_url`).

Both backends run the same SQL through one :class:`~service.storage.store.JobStore`; a backend only
opens a transaction on a connection and says its placeholder style (queries are written with ``?``).
The API process and every worker process open the store; each operation is one transaction. SQLite
opens a short-lived connection per transaction; PostgreSQL borrows one from a per-process connection
pool (psycopg_pool, created on first use in each process, never pickled), so no connection crosses a
process and each is used by one thread at a time. Times are Unix seconds (float, stored as DOUBLE
PRECISION).
"""

from __future__ import annotations

import os
import re
import sqlite3
import threading
import uuid
import zlib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import unquote

from service.http_errors import Unavailable

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


class StoreBase:
    """What the store's parts (sessions, logs, chunks, jobs) stand on: a backend, and :meth:`_tx`, one
    transaction that takes ``?`` placeholders."""

    backend: Backend

    @contextmanager
    def _tx(self) -> Iterator[_Transaction]:
        with self.backend.transaction() as conn:
            yield _Transaction(conn, self.backend.placeholder)


# ---- LIDARMAP_DATABASE_URL ----------------------------------------------------------------------


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
