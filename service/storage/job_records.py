"""The job store's jobs: creation (one live job per session at most), the queued -> running claim,
progress, heartbeats, cancel requests, the terminal status, and the jobs whose worker was lost."""

from __future__ import annotations

import time
from typing import Any

from api_schemas.jobs import JobSource, JobStatus
from service.storage.database import StoreBase, _Transaction, new_id
from service.storage.rows import ACTIVE_STATUSES, TERMINAL_STATUSES, JobRow, dump_json
from service.storage.session_records import _lock_session

# SQL parameters are plain strings (a driver may adapt an Enum by its name)
_QUEUED, _RUNNING, _FAILED, _CANCELLED = (s.value for s in (JobStatus.QUEUED, JobStatus.RUNNING, JobStatus.FAILED,
                                                             JobStatus.CANCELLED))


class JobRecords(StoreBase):
    """Jobs (table ``jobs``); every method is one transaction."""

    def create_job(self, session_id: str, owner: str, source: JobSource, log_id: str | None,
                   config: dict[str, Any]) -> JobRow:
        """A new queued job."""
        job_id = new_id()
        with self._tx() as tx:
            _insert_job(tx, job_id, session_id, owner, JobSource(source), log_id, config)
            return _job_row(tx, job_id)

    def create_live_job(self, session_id: str, owner: str,
                        config: dict[str, Any]) -> tuple[JobRow | None, JobRow | None]:
        """A live stream job, unless the session has one queued or running: (new row, None) or
        (None, the active live job's row)."""
        job_id = new_id()
        with self._tx() as tx:
            _lock_session(tx, session_id)
            active = tx.execute(f"SELECT * FROM jobs WHERE session_id = ? AND status IN {_ACTIVE} "
                                "ORDER BY created_at", (session_id, *_ACTIVE_VALUES)).fetchall()
            for row in map(JobRow.from_db, active):
                if row.live:
                    return None, row
            _insert_job(tx, job_id, session_id, owner, JobSource.STREAM, None, config)
            return _job_row(tx, job_id), None

    def get_job(self, job_id: str, owner: str | None = None) -> JobRow | None:
        """The job, or None when unknown (or owned by someone else when ``owner`` is given)."""
        with self._tx() as tx:
            row = tx.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None or (owner is not None and row["owner"] != owner):
            return None
        return JobRow.from_db(row)

    def list_jobs(self, owner: str, session_id: str | None, status: JobStatus | None,
                  limit: int, offset: int) -> tuple[list[JobRow], int]:
        where, args = ["owner = ?"], [owner]
        if session_id is not None:
            where.append("session_id = ?")
            args.append(session_id)
        if status is not None:
            where.append("status = ?")
            args.append(JobStatus(status).value)
        clause = " AND ".join(where)
        with self._tx() as tx:
            rows = tx.execute(f"SELECT * FROM jobs WHERE {clause} ORDER BY created_at DESC LIMIT ? OFFSET ?",
                              (*args, limit, offset)).fetchall()
            count = tx.execute(f"SELECT count(*) AS n FROM jobs WHERE {clause}", args).fetchone()["n"]
        return [JobRow.from_db(r) for r in rows], int(count)

    def jobs_with_status(self, *statuses: JobStatus) -> list[str]:
        """Ids of the jobs in any of ``statuses``, oldest first."""
        marks = ", ".join("?" * len(statuses))
        with self._tx() as tx:
            rows = tx.execute(f"SELECT id FROM jobs WHERE status IN ({marks}) ORDER BY created_at",
                              [JobStatus(s).value for s in statuses])
            return [r["id"] for r in rows]

    def mark_running(self, job_id: str, worker_pid: int) -> bool:
        """The claim, queued -> running in one conditional update; False when the job is no longer
        queued (another worker claimed it, or it was cancelled meanwhile)."""
        now = time.time()
        with self._tx() as tx:
            cur = tx.execute("UPDATE jobs SET status = ?, started_at = ?, heartbeat_at = ?, "
                             "worker_pid = ? WHERE id = ? AND status = ? AND cancel_requested = 0",
                             (_RUNNING, now, now, worker_pid, job_id, _QUEUED))
            return cur.rowcount == 1

    def set_input(self, job_id: str, input_description: dict[str, Any]) -> None:
        with self._tx() as tx:
            tx.execute("UPDATE jobs SET input_json = ? WHERE id = ?", (dump_json(input_description), job_id))

    def update_progress(self, job_id: str, scans_done: int, scans_total: int | None,
                        progress: float | None = None) -> bool:
        """Record progress (``progress``: the job's share done, 0..1; default the scans' share) and
        heartbeat; returns whether a cancel was requested."""
        if progress is None:
            progress = 0.0 if not scans_total else scans_done / scans_total
        progress = min(1.0, max(0.0, progress))
        with self._tx() as tx:
            tx.execute("UPDATE jobs SET scans_done = ?, scans_total = ?, progress = ?, heartbeat_at = ? "
                       "WHERE id = ? AND status = ?",
                       (scans_done, scans_total, progress, time.time(), job_id, _RUNNING))
            row = tx.execute("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return row is None or bool(row["cancel_requested"])

    def cancel_requested(self, job_id: str) -> bool:
        with self._tx() as tx:
            row = tx.execute("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return row is None or bool(row["cancel_requested"])

    def set_products(self, job_id: str, products: dict[str, str]) -> None:
        """Product name -> file name inside the job's artifact folder."""
        with self._tx() as tx:
            tx.execute("UPDATE jobs SET products_json = ? WHERE id = ?", (dump_json(products), job_id))

    def finish(self, job_id: str, status: JobStatus, error: str | None = None) -> bool:
        """An active job -> a terminal status (first writer wins); False when already terminal."""
        status = JobStatus(status)
        if status not in TERMINAL_STATUSES:
            raise ValueError(f"a job finishes as one of {[s.value for s in TERMINAL_STATUSES]}, not {status.value!r}")
        with self._tx() as tx:
            extra = ", progress = 1.0" if status is JobStatus.SUCCEEDED else ""
            cur = tx.execute(f"UPDATE jobs SET status = ?, error = ?, finished_at = ?{extra} "
                             f"WHERE id = ? AND status IN {_ACTIVE}",
                             (status.value, error, time.time(), job_id, *_ACTIVE_VALUES))
            return cur.rowcount == 1

    def request_cancel(self, job_id: str) -> JobStatus | None:
        """Ask a job to stop: a queued job is cancelled at once, a running one is flagged for its
        worker. Returns the status afterwards (None: no such job)."""
        with self._tx() as tx:
            tx.execute(f"UPDATE jobs SET cancel_requested = 1 WHERE id = ? AND status IN {_ACTIVE}",
                       (job_id, *_ACTIVE_VALUES))
            tx.execute("UPDATE jobs SET status = ?, error = 'cancelled by request', finished_at = ? "
                       "WHERE id = ? AND status = ?", (_CANCELLED, time.time(), job_id, _QUEUED))
            row = tx.execute("SELECT status FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return None if row is None else JobStatus(row["status"])

    def heartbeat(self, job_id: str) -> bool:
        """A running job's worker is alive; returns whether the job should stop (cancel requested,
        or no longer running because it was failed meanwhile)."""
        with self._tx() as tx:
            tx.execute("UPDATE jobs SET heartbeat_at = ? WHERE id = ? AND status = ?",
                       (time.time(), job_id, _RUNNING))
            row = tx.execute("SELECT status, cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return row is None or row["status"] != JobStatus.RUNNING or bool(row["cancel_requested"])

    def fail_lost(self, silent_s: float) -> list[str]:
        """Running jobs whose heartbeat is older than ``silent_s`` -> failed 'worker lost' (their
        cancel flag is set too, so a worker that was only slow stops at its next progress report).
        Each update re-checks the heartbeat: one that arrives meanwhile keeps its job running."""
        now = time.time()
        silent = "status = ? AND coalesce(heartbeat_at, started_at, 0) < ?"
        failed = []
        with self._tx() as tx:
            rows = tx.execute(f"SELECT id, heartbeat_at, worker_pid FROM jobs WHERE {silent}",
                              (_RUNNING, now - silent_s)).fetchall()
            for row in rows:
                silence = f"{now - row['heartbeat_at']:.0f} s" if row["heartbeat_at"] else "ever"
                reason = (f"worker lost: no heartbeat for {silence} (worker pid {row['worker_pid']}): its process "
                          "or machine stopped")
                cur = tx.execute(f"UPDATE jobs SET status = ?, cancel_requested = 1, finished_at = ?, "
                                 f"error = ? WHERE id = ? AND {silent}",
                                 (_FAILED, now, reason, row["id"], _RUNNING, now - silent_s))
                if cur.rowcount == 1:
                    failed.append(row["id"])
        return failed

    def fail_interrupted(self) -> list[str]:
        """At start-up: jobs left 'running' by a previous process cannot resume -> failed 'interrupted'."""
        with self._tx() as tx:
            rows = tx.execute("UPDATE jobs SET status = ?, finished_at = ?, error = 'interrupted: the "
                              "service stopped while the job was running' WHERE status = ? RETURNING id",
                              (_FAILED, time.time(), _RUNNING)).fetchall()
        return [r["id"] for r in rows]


_ACTIVE_VALUES = tuple(status.value for status in ACTIVE_STATUSES)  # SQL parameters: plain strings
_ACTIVE = "(" + ", ".join("?" * len(_ACTIVE_VALUES)) + ")"  # their placeholders


def _insert_job(tx: _Transaction, job_id: str, session_id: str, owner: str, source: JobSource, log_id: str | None,
                config: dict[str, Any]) -> None:
    tx.execute("INSERT INTO jobs (id, session_id, owner, source, log_id, config_json, status, created_at) "
               "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
               (job_id, session_id, owner, source.value, log_id, dump_json(config), _QUEUED, time.time()))


def _job_row(tx: _Transaction, job_id: str) -> JobRow:
    return JobRow.from_db(tx.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone())
