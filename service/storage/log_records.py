"""The job store's uploaded logs: a session's uploads, numbered 1, 2, ... in the order they arrived."""

from __future__ import annotations

import time
from typing import Any

from sqlalchemy import func, insert, select

from service.storage.database import StoreBase
from service.storage.rows import LogRow, dump_json
from service.storage.session_records import _lock_session
from service.storage.tables import jobs, logs, sessions


class LogRecords(StoreBase):
    """Uploaded logs (table ``logs``); every method is one transaction."""

    def add_log(self, log_id: str, session_id: str, filename: str, size_bytes: int, sha256: str,
                archive: bool, summary: dict[str, Any], stored_path: str) -> LogRow | None:
        """``stored_path``: where the log lies, relative to the data folder (built from ids only).
        None (nothing stored) when the session no longer exists."""
        row = {"id": log_id, "session_id": session_id, "filename": filename, "size_bytes": size_bytes,
               "sha256": sha256, "archive": int(archive), "format": summary.get("format", "unknown"),
               "summary_json": dump_json(summary), "stored_path": stored_path, "created_at": time.time()}
        next_upload_no = (select(func.coalesce(func.max(logs.c.upload_no), 0) + 1)
                          .where(logs.c.session_id == session_id).scalar_subquery())
        with self._tx() as tx:
            _lock_session(tx, session_id)
            if tx.execute(select(sessions.c.id).where(sessions.c.id == session_id)).first() is None:
                return None  # the session was deleted while the log arrived
            tx.execute(insert(logs).values(**row, upload_no=next_upload_no))
        return LogRow.from_db(row)

    def stored_ids(self) -> dict[str, set[str]]:
        """Every session, log and job id in the store (to find files that nothing refers to)."""
        with self._tx() as tx:
            return {table.name: set(tx.execute(select(table.c.id)).scalars()) for table in (sessions, logs, jobs)}

    def get_log(self, log_id: str, session_id: str) -> LogRow | None:
        with self._tx() as tx:
            row = tx.execute(select(logs).where(logs.c.id == log_id, logs.c.session_id == session_id)
                             ).mappings().first()
        return None if row is None else LogRow.from_db(row)

    def list_logs(self, session_id: str) -> list[LogRow]:
        """Logs of a session, newest first."""
        with self._tx() as tx:
            rows = tx.execute(select(logs).where(logs.c.session_id == session_id)
                              .order_by(logs.c.upload_no.desc(), logs.c.created_at.desc())).mappings().all()
        return [LogRow.from_db(r) for r in rows]
