"""The job store: sessions, uploaded logs, streamed chunks and jobs, in SQLite (the default: one
file in WAL mode) or PostgreSQL (``LIDARMAP_DATABASE_URL=postgresql://...``, for several hosts).

:class:`JobStore` puts together each resource's persistence: sessions (``session_records.py``),
uploaded logs (``log_records.py``), streamed chunks and the stream's end (``chunk_records.py``) and
jobs (``job_records.py``), over ``database.py``: the SQLite and PostgreSQL backends (SQLAlchemy
engines) and the transaction every operation runs in. The tables are SQLAlchemy Core metadata
(``tables.py``), created and upgraded by Alembic's migrations (``migration.py``,
``migrations/versions``) when the store is initialised. :func:`open_store` opens the store that
``LIDARMAP_DATABASE_URL`` names.

Atomicity: SQLite's ``BEGIN IMMEDIATE`` runs transactions one after another. PostgreSQL runs them
concurrently (READ COMMITTED), so every check-then-write is one conditional statement (the
queued -> running claim is ``UPDATE ... WHERE status = 'queued'``: a concurrent claimer waits for
the row lock, re-reads the row and updates nothing) and chunk inserts use ``ON CONFLICT``.
Checks that span rows of a session (a chunk beyond the stream's end, one live job per session)
first lock the session's row with a no-op ``UPDATE``
(:func:`~service.storage.session_records._lock_session`), so those transactions run one after
another on both backends.
"""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import func, select

from service.storage.chunk_records import ChunkOutcome, ChunkRecords, FinishOutcome
from service.storage.database import (
    POSTGRES_CONNECT_TIMEOUT_S,
    POSTGRES_POOL_MAX_CONNECTIONS,
    POSTGRES_QUICK_BORROW_S,
    Backend,
    PostgresBackend,
    SqliteBackend,
    StoreUnavailable,
    new_id,
    safe_url,
)
from service.storage.job_records import JobRecords
from service.storage.log_records import LogRecords
from service.storage.session_records import SessionRecords
from service.storage.tables import jobs

__all__ = [
    "POSTGRES_CONNECT_TIMEOUT_S",
    "POSTGRES_POOL_MAX_CONNECTIONS",
    "POSTGRES_QUICK_BORROW_S",
    "Backend",
    "ChunkOutcome",
    "ChunkRecords",
    "FinishOutcome",
    "JobRecords",
    "JobStore",
    "LogRecords",
    "PostgresBackend",
    "SessionRecords",
    "SqliteBackend",
    "StoreUnavailable",
    "new_id",
    "open_store",
    "safe_url",
]


class JobStore(SessionRecords, LogRecords, ChunkRecords, JobRecords):
    """The service's persistence; every method is one transaction. ``JobStore(path)`` is SQLite
    at ``path``; pass a :class:`PostgresBackend` for PostgreSQL (or use :func:`open_store`)."""

    def __init__(self, backend: Backend | Path):
        self.backend = backend if isinstance(backend, SqliteBackend | PostgresBackend) else SqliteBackend(backend)

    def __repr__(self) -> str:
        return f"JobStore({self.backend!r})"

    def close(self) -> None:
        """Close this process's pooled connections (PostgreSQL); SQLite holds none between transactions."""
        self.backend.close()

    def initialise(self) -> None:
        """Create or upgrade the schema with Alembic's migrations (idempotent; one process at a time;
        SQLite: the file too, in WAL mode)."""
        self.backend.create_schema()

    def ping(self) -> bool:
        """True when the database answers a query."""
        try:
            with self._tx() as tx:
                tx.execute(select(func.count()).select_from(jobs)).scalar()
            return True
        except self.backend.errors:
            return False


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
