"""The job store's uploaded logs: a session's uploads, numbered 1, 2, ... in the order they arrived."""

from __future__ import annotations

import time
from typing import Any

from service.storage.database import StoreBase
from service.storage.rows import LogRow, dump_json
from service.storage.session_records import _lock_session


class LogRecords(StoreBase):
    """Uploaded logs (table ``logs``); every method is one transaction."""

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
