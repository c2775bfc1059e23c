"""The job store's sessions: a user's recordings, with the number of logs, chunks and jobs in each.
Deleting a session deletes all of them. :func:`_lock_session` serialises the checks that span rows of
a session (the logs, chunks and jobs modules take it too).
"""

from __future__ import annotations

import time
from typing import Any

from service.storage.database import StoreBase, _Transaction, new_id
from service.storage.rows import SessionRow, dump_json


class SessionRecords(StoreBase):
    """Sessions (table ``sessions``); every method is one transaction."""

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


def _lock_session(tx: _Transaction, session_id: str) -> None:
    """Hold the session's row lock until the transaction ends (PostgreSQL; SQLite's BEGIN IMMEDIATE
    already serialises every transaction)."""
    tx.execute("UPDATE sessions SET id = id WHERE id = ?", (session_id,))


_SESSION_SELECT = (
    "SELECT s.*, (SELECT count(*) FROM logs l WHERE l.session_id = s.id) AS n_logs, "
    "(SELECT count(*) FROM chunks c WHERE c.session_id = s.id) AS n_chunks, "
    "(SELECT count(*) FROM jobs j WHERE j.session_id = s.id) AS n_jobs FROM sessions s"
)
