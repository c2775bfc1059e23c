"""The job store's sessions: a user's recordings, with the number of logs, chunks and jobs in each.
Deleting a session deletes all of them. :func:`_lock_session` serialises the checks that span rows of
a session (the logs, chunks and jobs modules take it too).
"""

from __future__ import annotations

import time
from typing import Any

from sqlalchemy import Connection, Select, delete, func, insert, select, update

from service.storage.database import StoreBase, new_id
from service.storage.rows import SessionRow, dump_json
from service.storage.tables import SESSION_TABLES, chunks, jobs, logs, sessions


class SessionRecords(StoreBase):
    """Sessions (table ``sessions``); every method is one transaction."""

    def create_session(self, owner: str, name: str, vehicle_preset: str | None,
                       calibration: dict[str, Any] | None, geo: dict[str, Any] | None) -> SessionRow:
        session_id = new_id()
        with self._tx() as tx:
            tx.execute(insert(sessions).values(
                id=session_id, owner=owner, name=name, vehicle_preset=vehicle_preset,
                calibration_json=dump_json(calibration), geo_json=dump_json(geo), created_at=time.time()))
            row = tx.execute(_session_select().where(sessions.c.id == session_id)).mappings().one()
        return SessionRow.from_db(row)

    def get_session(self, session_id: str, owner: str) -> SessionRow | None:
        with self._tx() as tx:
            row = tx.execute(_session_select().where(sessions.c.id == session_id, sessions.c.owner == owner)
                             ).mappings().first()
        return None if row is None else SessionRow.from_db(row)

    def list_sessions(self, owner: str, limit: int, offset: int) -> tuple[list[SessionRow], int]:
        with self._tx() as tx:
            rows = tx.execute(_session_select().where(sessions.c.owner == owner)
                              .order_by(sessions.c.created_at.desc()).limit(limit).offset(offset)).mappings().all()
            count = tx.execute(select(func.count()).select_from(sessions).where(sessions.c.owner == owner)).scalar()
        return [SessionRow.from_db(r) for r in rows], int(count or 0)

    def delete_session(self, session_id: str) -> list[str]:
        """Delete the session with its logs, chunks and jobs; returns the deleted job ids."""
        with self._tx() as tx:
            job_ids = list(tx.execute(select(jobs.c.id).where(jobs.c.session_id == session_id)).scalars())
            for table in SESSION_TABLES:
                tx.execute(delete(table).where(table.c.session_id == session_id))
            tx.execute(delete(sessions).where(sessions.c.id == session_id))
        return job_ids


def _lock_session(tx: Connection, session_id: str) -> None:
    """Hold the session's row lock until the transaction ends (PostgreSQL; SQLite's BEGIN IMMEDIATE
    already serialises every transaction)."""
    tx.execute(update(sessions).where(sessions.c.id == session_id).values(id=sessions.c.id))


def _session_select() -> Select[Any]:
    """A session's columns with the counts of its logs, chunks and jobs (n_logs, n_chunks, n_jobs)."""
    def count_of(table: Any, label: str) -> Any:
        return (select(func.count()).select_from(table).where(table.c.session_id == sessions.c.id)
                .scalar_subquery().label(label))

    return select(sessions, count_of(logs, "n_logs"), count_of(chunks, "n_chunks"), count_of(jobs, "n_jobs"))
