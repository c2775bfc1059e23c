"""The job store's jobs: creation (one live job per session at most), the queued -> running claim,
progress, heartbeats, cancel requests, the terminal status, and the jobs whose worker was lost."""

from __future__ import annotations

import time
from typing import Any

from sqlalchemy import Connection, func, insert, literal, select, update

from api_schemas.jobs import JobSource, JobStatus
from service.storage.database import StoreBase, new_id
from service.storage.rows import ACTIVE_STATUSES, TERMINAL_STATUSES, JobRow, dump_json
from service.storage.session_records import _lock_session
from service.storage.tables import jobs

# SQL parameters are plain strings (a driver may adapt an Enum by its name)
_QUEUED, _RUNNING, _FAILED, _CANCELLED = (s.value for s in (JobStatus.QUEUED, JobStatus.RUNNING, JobStatus.FAILED,
                                                             JobStatus.CANCELLED))
_ACTIVE_VALUES = tuple(status.value for status in ACTIVE_STATUSES)


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
            active = tx.execute(select(jobs).where(jobs.c.session_id == session_id,
                                                   jobs.c.status.in_(_ACTIVE_VALUES))
                                .order_by(jobs.c.created_at)).mappings().all()
            for row in map(JobRow.from_db, active):
                if row.live:
                    return None, row
            _insert_job(tx, job_id, session_id, owner, JobSource.STREAM, None, config)
            return _job_row(tx, job_id), None

    def get_job(self, job_id: str, owner: str | None = None) -> JobRow | None:
        """The job, or None when unknown (or owned by someone else when ``owner`` is given)."""
        with self._tx() as tx:
            row = tx.execute(select(jobs).where(jobs.c.id == job_id)).mappings().first()
        if row is None or (owner is not None and row["owner"] != owner):
            return None
        return JobRow.from_db(row)

    def list_jobs(self, owner: str, session_id: str | None, status: JobStatus | None,
                  limit: int, offset: int) -> tuple[list[JobRow], int]:
        where = [jobs.c.owner == owner]
        if session_id is not None:
            where.append(jobs.c.session_id == session_id)
        if status is not None:
            where.append(jobs.c.status == JobStatus(status).value)
        with self._tx() as tx:
            rows = tx.execute(select(jobs).where(*where).order_by(jobs.c.created_at.desc())
                              .limit(limit).offset(offset)).mappings().all()
            count = tx.execute(select(func.count()).select_from(jobs).where(*where)).scalar()
        return [JobRow.from_db(r) for r in rows], int(count or 0)

    def jobs_with_status(self, *statuses: JobStatus) -> list[str]:
        """Ids of the jobs in any of ``statuses``, oldest first."""
        values = [JobStatus(s).value for s in statuses]
        with self._tx() as tx:
            return list(tx.execute(select(jobs.c.id).where(jobs.c.status.in_(values))
                                   .order_by(jobs.c.created_at)).scalars())

    def mark_running(self, job_id: str, worker_pid: int) -> bool:
        """The claim, queued -> running in one conditional update; False when the job is no longer
        queued (another worker claimed it, or it was cancelled meanwhile)."""
        now = time.time()
        with self._tx() as tx:
            cur = tx.execute(update(jobs).where(jobs.c.id == job_id, jobs.c.status == _QUEUED,
                                                jobs.c.cancel_requested == 0)
                             .values(status=_RUNNING, started_at=now, heartbeat_at=now, worker_pid=worker_pid))
            return cur.rowcount == 1

    def set_input(self, job_id: str, input_description: dict[str, Any]) -> None:
        with self._tx() as tx:
            tx.execute(update(jobs).where(jobs.c.id == job_id).values(input_json=dump_json(input_description)))

    def update_progress(self, job_id: str, scans_done: int, scans_total: int | None,
                        progress: float | None = None) -> bool:
        """Record progress (``progress``: the job's share done, 0..1; default the scans' share) and
        heartbeat; returns whether the job should stop (a cancel was requested, or it is not running any
        more: failed as lost or interrupted meanwhile)."""
        if progress is None:
            progress = 0.0 if not scans_total else scans_done / scans_total
        progress = min(1.0, max(0.0, progress))
        with self._tx() as tx:
            tx.execute(update(jobs).where(jobs.c.id == job_id, jobs.c.status == _RUNNING)
                       .values(scans_done=scans_done, scans_total=scans_total, progress=progress,
                               heartbeat_at=time.time()))
            row = tx.execute(select(jobs.c.status, jobs.c.cancel_requested).where(jobs.c.id == job_id)).first()
        return row is None or row[0] != _RUNNING or bool(row[1])

    def owns(self, job_id: str, worker_pid: int) -> bool:
        """Whether the job is still running on the worker process ``worker_pid`` (not failed as lost or
        interrupted meanwhile): only then may that worker move its products in and finish it."""
        with self._tx() as tx:
            row = tx.execute(select(jobs.c.status, jobs.c.worker_pid).where(jobs.c.id == job_id)).first()
        return row is not None and row[0] == _RUNNING and row[1] == worker_pid

    def cancel_requested(self, job_id: str) -> bool:
        with self._tx() as tx:
            flag = tx.execute(select(jobs.c.cancel_requested).where(jobs.c.id == job_id)).first()
        return flag is None or bool(flag[0])

    def set_products(self, job_id: str, products: dict[str, str]) -> bool:
        """Product name -> file name inside the job's artifact folder, for a job still active; False (and
        nothing listed) once it is terminal, e.g. failed while a worker it no longer belongs to wrote."""
        with self._tx() as tx:
            cur = tx.execute(update(jobs).where(jobs.c.id == job_id, jobs.c.status.in_(_ACTIVE_VALUES))
                             .values(products_json=dump_json(products)))
            return cur.rowcount == 1

    def finish(self, job_id: str, status: JobStatus, error: str | None = None) -> bool:
        """An active job -> a terminal status (first writer wins); False when already terminal."""
        status = JobStatus(status)
        if status not in TERMINAL_STATUSES:
            raise ValueError(f"a job finishes as one of {[s.value for s in TERMINAL_STATUSES]}, not {status.value!r}")
        values: dict[str, Any] = {"status": status.value, "error": error, "finished_at": time.time()}
        if status is JobStatus.SUCCEEDED:
            values["progress"] = 1.0
        with self._tx() as tx:
            cur = tx.execute(update(jobs).where(jobs.c.id == job_id, jobs.c.status.in_(_ACTIVE_VALUES)).values(values))
            return cur.rowcount == 1

    def request_cancel(self, job_id: str) -> JobStatus | None:
        """Ask a job to stop: a queued job is cancelled at once, a running one is flagged for its
        worker. Returns the status afterwards (None: no such job)."""
        with self._tx() as tx:
            tx.execute(update(jobs).where(jobs.c.id == job_id, jobs.c.status.in_(_ACTIVE_VALUES))
                       .values(cancel_requested=1))
            tx.execute(update(jobs).where(jobs.c.id == job_id, jobs.c.status == _QUEUED)
                       .values(status=_CANCELLED, error="cancelled by request", finished_at=time.time()))
            status = tx.execute(select(jobs.c.status).where(jobs.c.id == job_id)).scalar()
        return None if status is None else JobStatus(status)

    def heartbeat(self, job_id: str) -> bool:
        """A running job's worker is alive; returns whether the job should stop (cancel requested,
        or no longer running because it was failed meanwhile)."""
        with self._tx() as tx:
            tx.execute(update(jobs).where(jobs.c.id == job_id, jobs.c.status == _RUNNING)
                       .values(heartbeat_at=time.time()))
            row = tx.execute(select(jobs.c.status, jobs.c.cancel_requested).where(jobs.c.id == job_id)).first()
        return row is None or row.status != JobStatus.RUNNING or bool(row.cancel_requested)

    def fail_lost(self, silent_s: float, disk_full: bool = False) -> list[str]:
        """Running jobs whose heartbeat is older than ``silent_s`` -> failed 'worker lost' (their
        cancel flag is set too, so a worker that was only slow stops at its next progress report);
        'disk full' when ``disk_full`` (the data folder has no space: the heartbeats could not be written).
        Each update re-checks the heartbeat: one that arrives meanwhile keeps its job running."""
        now = time.time()
        silent = (jobs.c.status == _RUNNING,
                  func.coalesce(jobs.c.heartbeat_at, jobs.c.started_at, literal(0.0)) < now - silent_s)
        failed = []
        with self._tx() as tx:
            rows = tx.execute(select(jobs.c.id, jobs.c.heartbeat_at, jobs.c.worker_pid).where(*silent)).all()
            for row in rows:
                silence = f"{now - row.heartbeat_at:.0f} s" if row.heartbeat_at else "ever"
                reason = (f"worker lost: no heartbeat for {silence} (worker pid {row.worker_pid}): its process "
                          "or machine stopped")
                if disk_full:
                    reason = (f"disk full: the service's data folder has no space left; no heartbeat for {silence} "
                              f"(worker pid {row.worker_pid}) could be written")
                cur = tx.execute(update(jobs).where(jobs.c.id == row.id, *silent)
                                 .values(status=_FAILED, cancel_requested=1, finished_at=now, error=reason))
                if cur.rowcount == 1:
                    failed.append(row.id)
        return failed

    def fail_interrupted(self) -> list[str]:
        """At start-up: jobs left 'running' by a previous process cannot resume -> failed 'interrupted'."""
        with self._tx() as tx:
            return list(tx.execute(
                update(jobs).where(jobs.c.status == _RUNNING)
                .values(status=_FAILED, finished_at=time.time(),
                        error="interrupted: the service stopped while the job was running")
                .returning(jobs.c.id)).scalars())


def _insert_job(tx: Connection, job_id: str, session_id: str, owner: str, source: JobSource, log_id: str | None,
                config: dict[str, Any]) -> None:
    tx.execute(insert(jobs).values(id=job_id, session_id=session_id, owner=owner, source=source.value, log_id=log_id,
                                   config_json=dump_json(config), status=_QUEUED, created_at=time.time()))


def _job_row(tx: Connection, job_id: str) -> JobRow:
    return JobRow.from_db(tx.execute(select(jobs).where(jobs.c.id == job_id)).mappings().one())
