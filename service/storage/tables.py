"""The job store's tables, as SQLAlchemy Core metadata: the one description of the schema that the
store's statements are built from and that Alembic's migrations (``service/storage/migrations``)
must produce (a test compares the two on SQLite and PostgreSQL).

Times are Unix seconds (DOUBLE PRECISION: PostgreSQL's REAL would be a 4-byte float, timestamps off
by minutes); counts and sizes are BIGINT; flags are INTEGER 0/1. ``logs.upload_no`` numbers a
session's uploads 1, 2, ... ("newest" must not depend on clock ties).
"""

from __future__ import annotations

from sqlalchemy import (
    DOUBLE_PRECISION,
    BigInteger,
    Column,
    Index,
    Integer,
    MetaData,
    PrimaryKeyConstraint,
    Table,
    Text,
    text,
)

metadata = MetaData()

sessions = Table(
    "sessions", metadata,
    Column("id", Text, primary_key=True),
    Column("owner", Text, nullable=False),
    Column("name", Text, nullable=False),
    Column("vehicle_preset", Text),
    Column("calibration_json", Text),
    Column("geo_json", Text),
    Column("created_at", DOUBLE_PRECISION, nullable=False),
)

logs = Table(
    "logs", metadata,
    Column("id", Text, primary_key=True),
    Column("session_id", Text, nullable=False),
    Column("filename", Text, nullable=False),
    Column("size_bytes", BigInteger, nullable=False),
    Column("sha256", Text, nullable=False),
    Column("archive", Integer, nullable=False),
    Column("format", Text, nullable=False),
    Column("summary_json", Text, nullable=False),
    Column("stored_path", Text, nullable=False),
    Column("created_at", DOUBLE_PRECISION, nullable=False),
    Column("upload_no", BigInteger, nullable=False, server_default=text("0")),
    Index("logs_session", "session_id", "created_at"),
)

chunks = Table(
    "chunks", metadata,
    Column("session_id", Text, nullable=False),
    Column("seq", BigInteger, nullable=False, autoincrement=False),
    Column("sha256", Text, nullable=False),
    Column("messages", BigInteger, nullable=False),
    Column("t_first_s", DOUBLE_PRECISION, nullable=False),
    Column("t_last_s", DOUBLE_PRECISION, nullable=False),
    Column("created_at", DOUBLE_PRECISION, nullable=False),
    PrimaryKeyConstraint("session_id", "seq"),
)

jobs = Table(
    "jobs", metadata,
    Column("id", Text, primary_key=True),
    Column("session_id", Text, nullable=False),
    Column("owner", Text, nullable=False),
    Column("source", Text, nullable=False),
    Column("log_id", Text),
    Column("config_json", Text, nullable=False),
    Column("status", Text, nullable=False),
    Column("progress", DOUBLE_PRECISION, nullable=False, server_default=text("0")),
    Column("scans_done", BigInteger, nullable=False, server_default=text("0")),
    Column("scans_total", BigInteger),
    Column("error", Text),
    Column("cancel_requested", Integer, nullable=False, server_default=text("0")),
    Column("input_json", Text),
    Column("products_json", Text),
    Column("worker_pid", BigInteger),
    Column("created_at", DOUBLE_PRECISION, nullable=False),
    Column("started_at", DOUBLE_PRECISION),
    Column("finished_at", DOUBLE_PRECISION),
    Column("heartbeat_at", DOUBLE_PRECISION),
    Index("jobs_session", "session_id", "created_at"),
    Index("jobs_status", "status"),
)

stream_ends = Table(
    "stream_ends", metadata,
    Column("session_id", Text, primary_key=True),
    Column("last_seq", BigInteger, nullable=False),
    Column("finished_at", DOUBLE_PRECISION, nullable=False),
)

SESSION_TABLES = (logs, chunks, jobs, stream_ends)  # the tables whose rows belong to a session (session_id)
