"""The job store's database: the two backends (SQLite, the default: one file in WAL mode;
PostgreSQL, ``LIDARMAP_DATABASE_URL=postgresql://...``, for several hosts), each a SQLAlchemy engine;
the transaction that every operation of the store runs in (:class:`StoreBase`); and
``LIDARMAP_DATABASE_URL`` made safe for messages (:func:`safe_url`).

The tables are SQLAlchemy Core metadata (``tables.py``) and every statement is built from them, so
both backends run the same statements; the schema is created and upgraded by Alembic's migrations
(``migration.py``) when the store is initialised. The API process and every worker process open the
store; each operation is one transaction. Each process makes its own engine on first use (an engine
is never pickled, and a forked child makes a new one), and each transaction borrows a connection
from that engine's pool, so no connection crosses a process and each is used by one thread at a
time: SQLite keeps :data:`SQLITE_OPEN_CONNECTIONS` open (closing the last one of a WAL file
checkpoints it: 10-15 ms per write when every transaction opened its own); PostgreSQL at most
:data:`POSTGRES_POOL_MAX_CONNECTIONS`, each checked before it is lent. Times are Unix seconds (float, DOUBLE PRECISION).
"""

from __future__ import annotations

import os
import re
import sqlite3
import threading
import time
import uuid
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import unquote

from sqlalchemy import Connection, Engine, create_engine, event, func, select
from sqlalchemy import exc as sa_exc

from service.http_errors import POSTGRES_DISK_FULL, Unavailable

POSTGRES_CONNECT_TIMEOUT_S = 10
POSTGRES_POOL_MAX_CONNECTIONS = 10  # per process: the API's request threads share them, a worker uses one
POSTGRES_QUICK_BORROW_S = 1.0  # a pooled connection not lent within this long: check the server directly
SQLITE_BUSY_TIMEOUT_S = 30.0  # how long a transaction waits for another process's write lock
SQLITE_OPEN_CONNECTIONS = 5  # kept open per process (more are opened, then closed, while many transactions wait)


class StoreUnavailable(Unavailable):
    """The database cannot be reached (503); the message never contains a password."""


def new_id() -> str:
    """A random UUID4 string: every id the service hands out."""
    return str(uuid.uuid4())


class _EnginePerProcess:
    """A SQLAlchemy engine made on first use in each process (a pickled backend carries none)."""

    def __init__(self) -> None:
        self._engine: Engine | None = None
        self._engine_pid: int | None = None
        self._engine_lock = threading.Lock()

    def _make_engine(self) -> Engine:
        raise NotImplementedError

    def engine(self) -> Engine:
        """This process's engine (a forked child makes a new one: the parent's connections are not its)."""
        with self._engine_lock:
            if self._engine is None or self._engine_pid != os.getpid():
                self._engine, self._engine_pid = self._make_engine(), os.getpid()
            return self._engine

    def close(self) -> None:
        """Close this process's pooled connections; the next transaction opens new ones."""
        with self._engine_lock:
            if self._engine is not None and self._engine_pid == os.getpid():
                self._engine.dispose()
            self._engine, self._engine_pid = None, None


# ---- backends -----------------------------------------------------------------------------------


class SqliteBackend(_EnginePerProcess):
    """One SQLite file in WAL mode, on a disk of this host (its locking is unsafe on network file
    systems). ``BEGIN IMMEDIATE`` makes every transaction take the write lock at once. Errors are
    the driver's (``sqlite3.Error``: a full disk is recognised by the API)."""

    def __init__(self, path: Path):
        super().__init__()
        self.path = Path(path)

    def __getstate__(self) -> dict[str, Any]:
        return {"path": self.path}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["path"])  # type: ignore[misc]

    def __repr__(self) -> str:
        return f"SqliteBackend({str(self.path)!r})"

    @property
    def errors(self) -> tuple[type[Exception], ...]:
        return (sqlite3.Error, sa_exc.SQLAlchemyError)

    def _make_engine(self) -> Engine:
        engine = create_engine(f"sqlite:///{self.path}", pool_size=SQLITE_OPEN_CONNECTIONS, max_overflow=-1,
                               connect_args={"timeout": SQLITE_BUSY_TIMEOUT_S})

        @event.listens_for(engine, "connect")
        def _driver_leaves_transactions_to_us(dbapi_connection: Any, _record: Any) -> None:
            dbapi_connection.isolation_level = None

        @event.listens_for(engine, "begin")
        def _take_the_write_lock(conn: Connection) -> None:
            conn.exec_driver_sql("BEGIN IMMEDIATE")

        return engine

    @contextmanager
    def transaction(self) -> Iterator[Connection]:
        try:
            with self.engine().begin() as conn:
                yield conn
        except sa_exc.DBAPIError as exc:
            if isinstance(exc.orig, sqlite3.Error):
                raise exc.orig from exc  # the driver's error, as the API's handlers know it
            raise

    def create_schema(self) -> None:
        from service.storage.migration import upgrade_schema  # imported when used (Alembic)

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._write_ahead_log()
        with self.transaction() as connection:
            upgrade_schema(connection)

    def _write_ahead_log(self) -> None:
        """Put the file in WAL mode (kept by the file; not allowed inside a transaction). The switch needs
        the file to itself, and SQLite answers "database is locked" at once, without waiting its busy
        timeout, while another process that opened it at the same moment holds a lock (the API and its
        workers starting on a new database: 2 starts of 60 with six stores failed so): tried again until
        the busy timeout."""
        deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_S
        while True:
            conn = sqlite3.connect(self.path, timeout=SQLITE_BUSY_TIMEOUT_S, isolation_level=None)
            try:
                conn.execute("PRAGMA journal_mode = WAL")
                return
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() > deadline:
                    raise
            finally:
                conn.close()
            time.sleep(0.02)


class PostgresBackend(_EnginePerProcess):
    """A PostgreSQL database (psycopg 3) that the API and the workers of every host reach."""

    _SCHEMA_LOCK = zlib.crc32(b"lidarmap job store schema")  # serialises concurrent migrations

    def __init__(self, url: str):
        super().__init__()
        self.url = url

    def __getstate__(self) -> dict[str, Any]:
        return {"url": self.url}  # a worker process builds its own engine

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["url"])  # type: ignore[misc]

    def __repr__(self) -> str:
        return f"PostgresBackend({safe_url(self.url)!r})"

    @property
    def errors(self) -> tuple[type[Exception], ...]:
        return (_psycopg().Error, sa_exc.SQLAlchemyError, StoreUnavailable)

    def _make_engine(self) -> Engine:
        _psycopg()
        rest = self.url.partition("://")[2]
        return create_engine(
            f"postgresql+psycopg://{rest}", pool_size=POSTGRES_POOL_MAX_CONNECTIONS, max_overflow=0,
            pool_timeout=POSTGRES_QUICK_BORROW_S, pool_pre_ping=True,
            connect_args={"connect_timeout": POSTGRES_CONNECT_TIMEOUT_S, "application_name": "lidarmap"})

    @contextmanager
    def transaction(self) -> Iterator[Connection]:
        try:
            with self._borrow() as conn, conn.begin():  # commits when the block succeeds, else rolls back
                yield conn
        except sa_exc.OperationalError as exc:  # the server went away, or refused the connection
            if isinstance(exc.orig, Exception) and getattr(exc.orig, "sqlstate", None) == POSTGRES_DISK_FULL:
                raise exc.orig from exc  # a full disk: 507, not 503
            raise self._unavailable(exc.orig or exc) from None

    def _borrow(self) -> Connection:
        """A pooled connection; when none is lent at once and a direct connection fails too (server
        down, wrong password) say why at once; otherwise every connection is busy: wait longer."""
        engine = self.engine()
        try:
            return engine.connect()
        except sa_exc.TimeoutError:
            pass
        psycopg = _psycopg()
        try:
            psycopg.connect(self.url, connect_timeout=POSTGRES_CONNECT_TIMEOUT_S).close()
        except psycopg.Error as exc:
            raise self._unavailable(exc) from None
        deadline = time.monotonic() + POSTGRES_CONNECT_TIMEOUT_S
        while True:
            try:
                return engine.connect()
            except sa_exc.TimeoutError:
                if time.monotonic() > deadline:
                    raise self._unavailable(RuntimeError(
                        f"all {POSTGRES_POOL_MAX_CONNECTIONS} pooled connections stayed busy for "
                        f"{POSTGRES_CONNECT_TIMEOUT_S} s")) from None

    def create_schema(self) -> None:
        from service.storage.migration import upgrade_schema  # imported when used: Alembic, ~0.1 s a worker never needs

        with self.transaction() as conn:
            conn.execute(select(func.pg_advisory_xact_lock(self._SCHEMA_LOCK)))
            upgrade_schema(conn)

    def _unavailable(self, exc: BaseException) -> StoreUnavailable:
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


Backend = SqliteBackend | PostgresBackend


class StoreBase:
    """What the store's parts (sessions, logs, chunks, jobs) stand on: a backend, and :meth:`_tx`, one
    transaction on a SQLAlchemy connection."""

    backend: Backend

    @contextmanager
    def _tx(self) -> Iterator[Connection]:
        with self.backend.transaction() as conn:
            yield conn


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
