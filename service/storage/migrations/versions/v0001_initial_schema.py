"""The job store's schema as the service created it before migrations (0.1.0): sessions, logs,
chunks, jobs and stream ends.

A database made by that code (its tables, no ``alembic_version``) is migrated by this revision too:
each table and index is created only where it is missing (``IF NOT EXISTS``, as that code did at
every start), and a ``logs`` table from before upload numbers gains ``upload_no`` (that code's
``ALTER``), so every database leaves this revision with the same schema.

Revision ID: 0001
Revises:
Created: 2026-11-26
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

_DOUBLE = sa.DOUBLE_PRECISION  # an 8-byte float on both databases (PostgreSQL's REAL has 4 bytes)


def upgrade() -> None:
    op.create_table(
        "sessions",
        sa.Column("id", sa.Text, primary_key=True),
        sa.Column("owner", sa.Text, nullable=False),
        sa.Column("name", sa.Text, nullable=False),
        sa.Column("vehicle_preset", sa.Text),
        sa.Column("calibration_json", sa.Text),
        sa.Column("geo_json", sa.Text),
        sa.Column("created_at", _DOUBLE, nullable=False),
        if_not_exists=True,
    )
    op.create_table(
        "logs",
        sa.Column("id", sa.Text, primary_key=True),
        sa.Column("session_id", sa.Text, nullable=False),
        sa.Column("filename", sa.Text, nullable=False),
        sa.Column("size_bytes", sa.BigInteger, nullable=False),
        sa.Column("sha256", sa.Text, nullable=False),
        sa.Column("archive", sa.Integer, nullable=False),
        sa.Column("format", sa.Text, nullable=False),
        sa.Column("summary_json", sa.Text, nullable=False),
        sa.Column("stored_path", sa.Text, nullable=False),
        sa.Column("created_at", _DOUBLE, nullable=False),
        sa.Column("upload_no", sa.BigInteger, nullable=False, server_default=sa.text("0")),
        if_not_exists=True,
    )
    if "upload_no" not in {c["name"] for c in sa.inspect(op.get_bind()).get_columns("logs")}:
        op.add_column("logs", sa.Column("upload_no", sa.BigInteger, nullable=False, server_default=sa.text("0")))
    op.create_index("logs_session", "logs", ["session_id", "created_at"], if_not_exists=True)
    op.create_table(
        "chunks",
        sa.Column("session_id", sa.Text, nullable=False),
        sa.Column("seq", sa.BigInteger, nullable=False, autoincrement=False),
        sa.Column("sha256", sa.Text, nullable=False),
        sa.Column("messages", sa.BigInteger, nullable=False),
        sa.Column("t_first_s", _DOUBLE, nullable=False),
        sa.Column("t_last_s", _DOUBLE, nullable=False),
        sa.Column("created_at", _DOUBLE, nullable=False),
        sa.PrimaryKeyConstraint("session_id", "seq"),
        if_not_exists=True,
    )
    op.create_table(
        "jobs",
        sa.Column("id", sa.Text, primary_key=True),
        sa.Column("session_id", sa.Text, nullable=False),
        sa.Column("owner", sa.Text, nullable=False),
        sa.Column("source", sa.Text, nullable=False),
        sa.Column("log_id", sa.Text),
        sa.Column("config_json", sa.Text, nullable=False),
        sa.Column("status", sa.Text, nullable=False),
        sa.Column("progress", _DOUBLE, nullable=False, server_default=sa.text("0")),
        sa.Column("scans_done", sa.BigInteger, nullable=False, server_default=sa.text("0")),
        sa.Column("scans_total", sa.BigInteger),
        sa.Column("error", sa.Text),
        sa.Column("cancel_requested", sa.Integer, nullable=False, server_default=sa.text("0")),
        sa.Column("input_json", sa.Text),
        sa.Column("products_json", sa.Text),
        sa.Column("worker_pid", sa.BigInteger),
        sa.Column("created_at", _DOUBLE, nullable=False),
        sa.Column("started_at", _DOUBLE),
        sa.Column("finished_at", _DOUBLE),
        sa.Column("heartbeat_at", _DOUBLE),
        if_not_exists=True,
    )
    op.create_index("jobs_session", "jobs", ["session_id", "created_at"], if_not_exists=True)
    op.create_index("jobs_status", "jobs", ["status"], if_not_exists=True)
    op.create_table(
        "stream_ends",
        sa.Column("session_id", sa.Text, primary_key=True),
        sa.Column("last_seq", sa.BigInteger, nullable=False),
        sa.Column("finished_at", _DOUBLE, nullable=False),
        if_not_exists=True,
    )


def downgrade() -> None:
    for table in ("stream_ends", "jobs", "chunks", "logs", "sessions"):
        op.drop_table(table)
