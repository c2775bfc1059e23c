"""The job store: sessions, uploaded logs, streamed chunks and jobs in one SQLite file (WAL).

Both the API process and the worker processes open it; each operation uses its own short-lived
connection, so no connection crosses a thread or process. Times are Unix seconds (float).
"""

from __future__ import annotations

import json
import sqlite3
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ACTIVE_STATUSES = ("queued", "running")
TERMINAL_STATUSES = ("succeeded", "failed", "cancelled")

SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY, owner TEXT NOT NULL, name TEXT NOT NULL, vehicle_preset TEXT,
    calibration_json TEXT, geo_json TEXT, created_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS logs (
    id TEXT PRIMARY KEY, session_id TEXT NOT NULL, filename TEXT NOT NULL, size_bytes INTEGER NOT NULL,
    sha256 TEXT NOT NULL, archive INTEGER NOT NULL, format TEXT NOT NULL, summary_json TEXT NOT NULL,
    stored_path TEXT NOT NULL, created_at REAL NOT NULL);
CREATE INDEX IF NOT EXISTS logs_session ON logs(session_id, created_at);
CREATE TABLE IF NOT EXISTS chunks (
    session_id TEXT NOT NULL, seq INTEGER NOT NULL, sha256 TEXT NOT NULL, messages INTEGER NOT NULL,
    t_first_s REAL NOT NULL, t_last_s REAL NOT NULL, created_at REAL NOT NULL,
    PRIMARY KEY (session_id, seq));
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY, session_id TEXT NOT NULL, owner TEXT NOT NULL, source TEXT NOT NULL, log_id TEXT,
    config_json TEXT NOT NULL, status TEXT NOT NULL, progress REAL NOT NULL DEFAULT 0,
    scans_done INTEGER NOT NULL DEFAULT 0, scans_total INTEGER, error TEXT,
    cancel_requested INTEGER NOT NULL DEFAULT 0, input_json TEXT, products_json TEXT,
    worker_pid INTEGER, created_at REAL NOT NULL, started_at REAL, finished_at REAL, heartbeat_at REAL);
CREATE INDEX IF NOT EXISTS jobs_session ON jobs(session_id, created_at);
CREATE INDEX IF NOT EXISTS jobs_status ON jobs(status);
"""


def new_id() -> str:
    """A random UUID4 string: every id the service hands out."""
    return str(uuid.uuid4())


@dataclass(frozen=True)
class ChunkOutcome:
    row: dict[str, Any]
    duplicate: bool
    conflict: bool


class JobStore:
    """SQLite-backed persistence; every method is one transaction."""

    def __init__(self, path: Path):
        self.path = Path(path)

    @contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        conn = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        conn.row_factory = sqlite3.Row
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

    def initialise(self) -> None:
        """Create the file and tables (idempotent) and switch the file to WAL."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        conn = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        try:
            conn.execute("PRAGMA journal_mode = WAL")
            conn.executescript(SCHEMA)
        finally:
            conn.close()

    def ping(self) -> bool:
        """True when the database answers a query."""
        try:
            with self._tx() as conn:
                conn.execute("SELECT count(*) FROM jobs").fetchone()
            return True
        except sqlite3.Error:
            return False

    # ---- sessions -------------------------------------------------------------------------------

    def create_session(self, owner: str, name: str, vehicle_preset: str | None,
                       calibration: dict | None, geo: dict | None) -> dict[str, Any]:
        row = {"id": new_id(), "owner": owner, "name": name, "vehicle_preset": vehicle_preset,
               "calibration_json": _dump(calibration), "geo_json": _dump(geo), "created_at": time.time()}
        with self._tx() as conn:
            conn.execute("INSERT INTO sessions VALUES (:id, :owner, :name, :vehicle_preset, "
                         ":calibration_json, :geo_json, :created_at)", row)
        return self.get_session(row["id"], owner)  # type: ignore[return-value]

    def get_session(self, session_id: str, owner: str) -> dict[str, Any] | None:
        with self._tx() as conn:
            row = conn.execute(_SESSION_SELECT + " WHERE s.id = ? AND s.owner = ?", (session_id, owner)).fetchone()
        return None if row is None else _session(row)

    def list_sessions(self, owner: str, limit: int, offset: int) -> tuple[list[dict[str, Any]], int]:
        with self._tx() as conn:
            rows = conn.execute(_SESSION_SELECT + " WHERE s.owner = ? ORDER BY s.created_at DESC LIMIT ? OFFSET ?",
                                (owner, limit, offset)).fetchall()
            count = conn.execute("SELECT count(*) FROM sessions WHERE owner = ?", (owner,)).fetchone()[0]
        return [_session(r) for r in rows], int(count)

    def delete_session(self, session_id: str) -> list[str]:
        """Delete the session with its logs, chunks and jobs; returns the deleted job ids."""
        with self._tx() as conn:
            job_ids = [r[0] for r in conn.execute("SELECT id FROM jobs WHERE session_id = ?", (session_id,))]
            for table in ("logs", "chunks", "jobs"):
                conn.execute(f"DELETE FROM {table} WHERE session_id = ?", (session_id,))
            conn.execute("DELETE FROM sessions WHERE id = ?", (session_id,))
        return job_ids

    # ---- logs -----------------------------------------------------------------------------------

    def add_log(self, log_id: str, session_id: str, filename: str, size_bytes: int, sha256: str,
                archive: bool, summary: dict, stored_path: str) -> dict[str, Any]:
        """``stored_path``: where the log lies, relative to the data folder (built from ids only)."""
        row = {"id": log_id, "session_id": session_id, "filename": filename, "size_bytes": size_bytes,
               "sha256": sha256, "archive": int(archive), "format": summary.get("format", "unknown"),
               "summary_json": _dump(summary), "stored_path": stored_path, "created_at": time.time()}
        with self._tx() as conn:
            conn.execute("INSERT INTO logs VALUES (:id, :session_id, :filename, :size_bytes, :sha256, :archive, "
                         ":format, :summary_json, :stored_path, :created_at)", row)
        return _log(row)

    def get_log(self, log_id: str, session_id: str) -> dict[str, Any] | None:
        with self._tx() as conn:
            row = conn.execute("SELECT * FROM logs WHERE id = ? AND session_id = ?", (log_id, session_id)).fetchone()
        return None if row is None else _log(dict(row))

    def list_logs(self, session_id: str) -> list[dict[str, Any]]:
        """Logs of a session, newest first."""
        with self._tx() as conn:
            rows = conn.execute("SELECT * FROM logs WHERE session_id = ? ORDER BY created_at DESC, rowid DESC",
                                (session_id,)).fetchall()
        return [_log(dict(r)) for r in rows]

    # ---- chunks ---------------------------------------------------------------------------------

    def put_chunk(self, session_id: str, seq: int, sha256: str, messages: int,
                  t_first_s: float, t_last_s: float) -> ChunkOutcome:
        """Record chunk ``seq`` once: a retry with the same hash is a duplicate, another hash a conflict."""
        with self._tx() as conn:
            old = conn.execute("SELECT * FROM chunks WHERE session_id = ? AND seq = ?", (session_id, seq)).fetchone()
            if old is not None:
                return ChunkOutcome(dict(old), duplicate=old["sha256"] == sha256, conflict=old["sha256"] != sha256)
            row = {"session_id": session_id, "seq": seq, "sha256": sha256, "messages": messages,
                   "t_first_s": t_first_s, "t_last_s": t_last_s, "created_at": time.time()}
            conn.execute("INSERT INTO chunks VALUES (:session_id, :seq, :sha256, :messages, :t_first_s, "
                         ":t_last_s, :created_at)", row)
        return ChunkOutcome(row, duplicate=False, conflict=False)

    def delete_chunk(self, session_id: str, seq: int) -> None:
        """Forget chunk ``seq`` (its file could not be written)."""
        with self._tx() as conn:
            conn.execute("DELETE FROM chunks WHERE session_id = ? AND seq = ?", (session_id, seq))

    def chunk_rows_near(self, session_id: str, seq: int) -> list[dict[str, Any]]:
        """Chunks seq-1, seq and seq+1 (what a new chunk is checked against), without reading the rest."""
        with self._tx() as conn:
            rows = conn.execute("SELECT * FROM chunks WHERE session_id = ? AND seq BETWEEN ? AND ? ORDER BY seq",
                                (session_id, seq - 1, seq + 1)).fetchall()
        return [dict(r) for r in rows]

    def stream_figures(self, session_id: str, max_after: int = 5000) -> dict[str, Any]:
        """The stream's state computed in SQL (cheap for long streams): chunks received, the end of
        the contiguous run from seq 0 (-1: none), the messages in it, the highest seq, and the
        seqs received beyond the run (at most ``max_after``, ascending)."""
        with self._tx() as conn:
            received, highest = conn.execute("SELECT count(*), max(seq) FROM chunks WHERE session_id = ?",
                                             (session_id,)).fetchone()
            k = conn.execute(
                "SELECT CASE WHEN EXISTS (SELECT 1 FROM chunks WHERE session_id = :s AND seq = 0) THEN "
                "(SELECT min(c.seq) FROM chunks c WHERE c.session_id = :s AND NOT EXISTS "
                "(SELECT 1 FROM chunks d WHERE d.session_id = :s AND d.seq = c.seq + 1)) ELSE -1 END",
                {"s": session_id}).fetchone()[0]
            messages = conn.execute("SELECT coalesce(sum(messages), 0) FROM chunks WHERE session_id = ? AND seq <= ?",
                                    (session_id, k)).fetchone()[0]
            after = [r[0] for r in conn.execute("SELECT seq FROM chunks WHERE session_id = ? AND seq > ? "
                                                "ORDER BY seq LIMIT ?", (session_id, k, max_after))]
        return {"received": int(received), "contiguous_through": int(k), "messages": int(messages),
                "highest": -1 if highest is None else int(highest), "after": after}

    def chunk_rows(self, session_id: str) -> list[dict[str, Any]]:
        """All chunks of a session in seq order."""
        with self._tx() as conn:
            rows = conn.execute("SELECT * FROM chunks WHERE session_id = ? ORDER BY seq", (session_id,)).fetchall()
        return [dict(r) for r in rows]

    # ---- jobs -----------------------------------------------------------------------------------

    def create_job(self, session_id: str, owner: str, source: str, log_id: str | None,
                   config: dict) -> dict[str, Any]:
        row = {"id": new_id(), "session_id": session_id, "owner": owner, "source": source, "log_id": log_id,
               "config_json": _dump(config), "status": "queued", "created_at": time.time()}
        with self._tx() as conn:
            conn.execute("INSERT INTO jobs (id, session_id, owner, source, log_id, config_json, status, created_at) "
                         "VALUES (:id, :session_id, :owner, :source, :log_id, :config_json, :status, :created_at)",
                         row)
        return self.get_job(row["id"])  # type: ignore[return-value]

    def get_job(self, job_id: str, owner: str | None = None) -> dict[str, Any] | None:
        """The job, or None when unknown (or owned by someone else when ``owner`` is given)."""
        with self._tx() as conn:
            row = conn.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None or (owner is not None and row["owner"] != owner):
            return None
        return _job(row)

    def list_jobs(self, owner: str, session_id: str | None, status: str | None,
                  limit: int, offset: int) -> tuple[list[dict[str, Any]], int]:
        where, args = ["owner = ?"], [owner]
        if session_id is not None:
            where.append("session_id = ?")
            args.append(session_id)
        if status is not None:
            where.append("status = ?")
            args.append(status)
        clause = " AND ".join(where)
        with self._tx() as conn:
            rows = conn.execute(f"SELECT * FROM jobs WHERE {clause} ORDER BY created_at DESC LIMIT ? OFFSET ?",
                                (*args, limit, offset)).fetchall()
            count = conn.execute(f"SELECT count(*) FROM jobs WHERE {clause}", args).fetchone()[0]
        return [_job(r) for r in rows], int(count)

    def jobs_with_status(self, *statuses: str) -> list[str]:
        marks = ",".join("?" * len(statuses))
        with self._tx() as conn:
            rows = conn.execute(f"SELECT id FROM jobs WHERE status IN ({marks}) ORDER BY created_at", statuses)
            return [r[0] for r in rows]

    def mark_running(self, job_id: str, worker_pid: int) -> bool:
        """queued -> running; False when the job is no longer queued (cancelled meanwhile)."""
        now = time.time()
        with self._tx() as conn:
            cur = conn.execute("UPDATE jobs SET status = 'running', started_at = ?, heartbeat_at = ?, "
                               "worker_pid = ? WHERE id = ? AND status = 'queued' AND cancel_requested = 0",
                               (now, now, worker_pid, job_id))
            return cur.rowcount == 1

    def set_input(self, job_id: str, input_description: dict) -> None:
        with self._tx() as conn:
            conn.execute("UPDATE jobs SET input_json = ? WHERE id = ?", (_dump(input_description), job_id))

    def update_progress(self, job_id: str, scans_done: int, scans_total: int | None) -> bool:
        """Record progress and heartbeat; returns whether a cancel was requested."""
        progress = 0.0 if not scans_total else min(1.0, max(0.0, scans_done / scans_total))
        with self._tx() as conn:
            conn.execute("UPDATE jobs SET scans_done = ?, scans_total = ?, progress = ?, heartbeat_at = ? "
                         "WHERE id = ? AND status = 'running'",
                         (scans_done, scans_total, progress, time.time(), job_id))
            row = conn.execute("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return row is None or bool(row[0])

    def cancel_requested(self, job_id: str) -> bool:
        with self._tx() as conn:
            row = conn.execute("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return row is None or bool(row[0])

    def set_products(self, job_id: str, products: dict[str, str]) -> None:
        """Product name -> file name inside the job's artifact folder."""
        with self._tx() as conn:
            conn.execute("UPDATE jobs SET products_json = ? WHERE id = ?", (_dump(products), job_id))

    def finish(self, job_id: str, status: str, error: str | None = None) -> bool:
        """An active job -> a terminal status (first writer wins); False when already terminal."""
        assert status in TERMINAL_STATUSES
        with self._tx() as conn:
            extra = ", progress = 1.0" if status == "succeeded" else ""
            cur = conn.execute(f"UPDATE jobs SET status = ?, error = ?, finished_at = ?{extra} "
                               "WHERE id = ? AND status IN ('queued', 'running')",
                               (status, error, time.time(), job_id))
            return cur.rowcount == 1

    def request_cancel(self, job_id: str) -> str:
        """Ask a job to stop: a queued job is cancelled at once, a running one is flagged for its
        worker. Returns the status afterwards."""
        with self._tx() as conn:
            conn.execute("UPDATE jobs SET cancel_requested = 1 WHERE id = ? AND status IN ('queued', 'running')",
                         (job_id,))
            conn.execute("UPDATE jobs SET status = 'cancelled', error = 'cancelled by request', finished_at = ? "
                         "WHERE id = ? AND status = 'queued'", (time.time(), job_id))
            row = conn.execute("SELECT status FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return "" if row is None else row[0]

    def fail_interrupted(self) -> list[str]:
        """At start-up: jobs left 'running' by a previous process cannot resume -> failed 'interrupted'."""
        with self._tx() as conn:
            ids = [r[0] for r in conn.execute("SELECT id FROM jobs WHERE status = 'running'")]
            conn.execute("UPDATE jobs SET status = 'failed', finished_at = ?, error = 'interrupted: the service "
                         "stopped while the job was running' WHERE status = 'running'", (time.time(),))
        return ids


_SESSION_SELECT = (
    "SELECT s.*, (SELECT count(*) FROM logs l WHERE l.session_id = s.id) AS n_logs, "
    "(SELECT count(*) FROM chunks c WHERE c.session_id = s.id) AS n_chunks, "
    "(SELECT count(*) FROM jobs j WHERE j.session_id = s.id) AS n_jobs FROM sessions s"
)


def _dump(value: Any) -> str | None:
    return None if value is None else json.dumps(value, sort_keys=True)


def _load(text: str | None) -> Any:
    return None if text is None else json.loads(text)


def _session(row: sqlite3.Row) -> dict[str, Any]:
    d = dict(row)
    return {"id": d["id"], "owner": d["owner"], "name": d["name"], "vehicle_preset": d["vehicle_preset"],
            "calibration": _load(d["calibration_json"]), "geo": _load(d["geo_json"]),
            "created_at": d["created_at"], "logs": d["n_logs"], "chunks": d["n_chunks"], "jobs": d["n_jobs"]}


def _log(d: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in d.items() if k not in ("summary_json", "format")}
    out["archive"] = bool(d["archive"])
    out["summary"] = _load(d["summary_json"])
    return out


def _job(row: sqlite3.Row) -> dict[str, Any]:
    d = dict(row)
    d["config"] = _load(d.pop("config_json"))
    d["input"] = _load(d.pop("input_json"))
    d["products"] = _load(d.pop("products_json")) or {}
    d["cancel_requested"] = bool(d["cancel_requested"])
    return d
