"""The embedded job runner, :class:`LocalProcessRunner`: a pool of spawned worker processes on this
machine (the default; the API talks only to the :class:`~service.runners.base.JobRunner` interface).

A supervisor thread hands queued job ids to idle workers, notices a worker that exits while it holds
a job (killed, crashed) and fails that job with the exit reason, replaces the worker, and kills
(SIGKILL, which also reaches a stopped process) a worker whose job ignores a cancel for longer than
the grace period. Each running job writes a heartbeat every ``heartbeat_s``; a job whose heartbeat is
older than ``worker_lost_s`` (its worker was stopped with SIGSTOP, or hangs with the interpreter
lock held) is failed "worker lost: no heartbeat for ..." and its worker killed and replaced.
An outcome the store refuses to take (a full disk) is kept and written again at each tick, a failing
tick logged once until ticks work again; on a full disk the data folder's spare file is given up for
these writes (:mod:`service.storage.disk_space`), and made again once there is room.
Workers die with the API process (:mod:`service.process_guard`).
A worker that has run ``max_jobs_per_worker`` jobs is asked to exit and replaced by a fresh one, so an
idle worker does not hold the memory its jobs left behind (the heap of a finished run is not given back
to the system).
"""

from __future__ import annotations

import functools
import logging
import multiprocessing as mp
import queue
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from api_schemas.jobs import JobStatus
from service.http_errors import LOW_SPACE_BYTES
from service.jobs.events import job_event
from service.runners.base import DEFAULT_JOB_FUNCTION, RunnerHealth
from service.storage.data_dir import DataDir
from service.storage.disk_space import keep_spare, write_status
from service.storage.store import JobStore

logger = logging.getLogger("lidarmap.runner")


def exit_reason(exitcode: int | None) -> str:
    """A person's words for a worker's exit code."""
    if exitcode is None:
        return "worker process vanished"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        return f"worker process died (killed by {name})"
    return f"worker process exited with code {exitcode}"


RESPAWN_BACKOFF_S = 2.0  # a worker that dies this soon after starting is replaced only after this pause


@dataclass
class _Slot:
    index: int
    process: Any
    inbox: Any
    started_s: float
    job_id: str | None = None
    respawn_at_s: float | None = None
    jobs_done: int = 0
    retiring: bool = False  # asked to exit after its jobs (max_jobs_per_worker): replaced when it has


class LocalProcessRunner:
    """A fixed number of long-lived worker processes (spawn start method) on this machine."""

    def __init__(self, data: DataDir, store: JobStore, workers: int, cancel_grace_s: float = 5.0,
                 job_function: str = DEFAULT_JOB_FUNCTION, poll_s: float = 0.05, memory_limit_mb: int = 0,
                 heartbeat_s: float = 5.0, worker_lost_s: float = 60.0, max_jobs_per_worker: int = 0):
        self._data = data
        self._heartbeat_s = heartbeat_s
        self._worker_lost_s = worker_lost_s
        self._next_reap_s = 0.0
        self._max_jobs_per_worker = max_jobs_per_worker
        self._memory_limit_mb = memory_limit_mb
        self._store = store
        self._job_function = job_function
        self._cancel_grace_s = cancel_grace_s
        self._poll_s = poll_s
        self._ctx = mp.get_context("spawn")
        self._outbox = self._ctx.Queue()
        self._lock = threading.Lock()
        self._pending: deque[str] = deque()
        self._cancel_asked: dict[str, float] = {}
        self._unwritten: dict[str, tuple[JobStatus, str]] = {}  # outcomes the store refused so far
        self._failing_since: float | None = None  # the first failed tick of the failures going on
        self._failed_ticks = 0
        keep_spare(data)
        self._stopping = threading.Event()
        self._slots = [self._spawn(i) for i in range(workers)]
        self._supervisor = threading.Thread(target=self._supervise, name="lidarmap-runner", daemon=True)
        self._supervisor.start()

    # ---- JobRunner ------------------------------------------------------------------------------

    def submit(self, job_id: str) -> None:
        with self._lock:
            self._pending.append(job_id)

    def cancel(self, job_id: str) -> None:
        with self._lock:
            self._cancel_asked.setdefault(job_id, time.monotonic())

    def health(self) -> RunnerHealth:
        with self._lock:
            alive = sum(slot.process.is_alive() for slot in self._slots)
            busy = sum(slot.job_id is not None for slot in self._slots)
            return RunnerHealth("local", len(self._slots), alive, busy, len(self._pending))

    def worker_pid(self, job_id: str) -> int | None:
        """The pid of the worker running ``job_id`` (for operators and tests)."""
        with self._lock:
            for slot in self._slots:
                if slot.job_id == job_id:
                    return slot.process.pid
        return None

    def shutdown(self) -> None:
        self._stopping.set()
        self._supervisor.join(timeout=5.0)
        try:
            self._write_unwritten()
        except Exception as exc:  # still refused: the next start fails them as interrupted
            logger.error("%d job outcomes could not be written at shutdown: %s", len(self._unwritten), exc)
        with self._lock:
            for slot in self._slots:
                if slot.job_id is None:
                    slot.inbox.put(None)
            for slot in self._slots:
                if slot.job_id is not None:
                    slot.process.terminate()
            for slot in self._slots:
                slot.process.join(timeout=5.0)
                if slot.process.is_alive():
                    slot.process.kill()
                    slot.process.join(timeout=2.0)
                if slot.job_id is not None:
                    reason = "interrupted: the service stopped while the job was running"
                    # a job whose worker finished it but whose message was not handled yet stays as
                    # it ended: only a job still active is failed (and logged so)
                    if self._store.finish(slot.job_id, JobStatus.FAILED, reason):
                        job_event(JobStatus.FAILED.value, slot.job_id, logging.WARNING, error=reason)
            for slot in self._slots:
                slot.inbox.close()
                slot.inbox.join_thread()
            self._slots = []
        self._outbox.close()
        self._outbox.join_thread()

    # ---- supervision ----------------------------------------------------------------------------

    def _spawn(self, index: int) -> _Slot:
        inbox = self._ctx.Queue()
        process = self._ctx.Process(
            target=_worker_entry, name=f"lidarmap-worker-{index}", daemon=True,
            args=(str(self._data.root), self._store, self._job_function, index, inbox, self._outbox,
                  self._memory_limit_mb, self._heartbeat_s, self._cancel_grace_s))
        process.start()
        return _Slot(index=index, process=process, inbox=inbox, started_s=time.monotonic())

    def _supervise(self) -> None:
        while not self._stopping.is_set():
            try:
                self._tick()
            except Exception:  # the supervisor must survive a bad tick (e.g. a locked database, a full disk)
                self._failed_ticks += 1
                if self._failing_since is None:  # once per incident, not at every tick (20 a second)
                    self._failing_since = time.monotonic()
                    logger.exception("runner supervisor tick failed (retried every %.2f s, logged once)", self._poll_s)
            else:
                if self._failing_since is not None:
                    logger.warning("runner supervisor ticks work again after %d failed in %.1f s", self._failed_ticks,
                                   time.monotonic() - self._failing_since)
                    self._failing_since, self._failed_ticks = None, 0
            self._stopping.wait(self._poll_s)

    def _tick(self) -> None:
        self._drain_outbox()
        with self._lock:  # no store writes here: a full disk does not keep a dead worker from being replaced
            for slot in list(self._slots):
                if not slot.process.is_alive():
                    self._replace_dead(slot)
            self._enforce_cancels()
            self._assign_pending()
        self._reap_silent()
        self._write_unwritten()

    def _reap_silent(self) -> None:
        """Every ``heartbeat_s``: fail the running jobs whose heartbeat is older than ``worker_lost_s``
        and kill their workers (SIGKILL: a stopped process cannot act on anything else)."""
        now = time.monotonic()
        if now < self._next_reap_s:
            return
        self._next_reap_s = now + self._heartbeat_s
        keep_spare(self._data)
        full = self._data.free_bytes() < LOW_SPACE_BYTES  # heartbeats that could not be written
        for job_id in write_status(self._data, lambda: self._store.fail_lost(self._worker_lost_s, disk_full=full)):
            logger.warning("job %s: no heartbeat for %.0f s: failed, its worker killed", job_id, self._worker_lost_s)
            with self._lock:
                for slot in self._slots:
                    if slot.job_id == job_id and slot.process.is_alive():
                        slot.process.kill()

    def _drain_outbox(self) -> None:
        while True:
            try:
                index, job_id, status, unwritten = self._outbox.get_nowait()
            except queue.Empty:
                return
            if unwritten is not None:  # its worker could not write the outcome
                self._unwritten[job_id] = (status, unwritten)
            with self._lock:
                slot = self._slots[index] if index < len(self._slots) else None
                if slot is not None and slot.job_id == job_id:
                    slot.job_id = None
                    slot.jobs_done += 1
                    if self._max_jobs_per_worker and slot.jobs_done >= self._max_jobs_per_worker:
                        slot.retiring = True  # it exits at this; _replace_dead starts a fresh one
                        slot.inbox.put(None)
                self._cancel_asked.pop(job_id, None)

    def _replace_dead(self, slot: _Slot) -> None:
        slot.process.join(timeout=0)
        if slot.retiring and slot.job_id is None and not self._stopping.is_set():
            slot.inbox.close()
            self._slots[slot.index] = self._spawn(slot.index)
            return
        reason = exit_reason(slot.process.exitcode)
        if slot.job_id is not None:
            asked = slot.job_id in self._cancel_asked
            self._data.remove(self._data.live_dir(slot.job_id))  # served only while it runs; freed before the write
            if asked:
                self._unwritten[slot.job_id] = (JobStatus.CANCELLED, "cancelled by request (worker stopped)")
            else:
                self._unwritten[slot.job_id] = (JobStatus.FAILED, reason)
            self._cancel_asked.pop(slot.job_id, None)
            slot.job_id = None
        if self._stopping.is_set():
            return
        now = time.monotonic()
        if slot.respawn_at_s is None:
            quick_death = now - slot.started_s < RESPAWN_BACKOFF_S
            slot.respawn_at_s = now + (RESPAWN_BACKOFF_S if quick_death else 0.0)
            if quick_death:
                logger.error("worker %d died %.1f s after starting (%s): respawning in %.0f s", slot.index,
                             now - slot.started_s, reason, RESPAWN_BACKOFF_S)
        if now >= slot.respawn_at_s:
            self._slots[slot.index] = self._spawn(slot.index)

    def _write_unwritten(self) -> None:
        """Write the outcomes the store refused so far (a full disk): each stays until it is written,
        and the worker slots are replaced meanwhile."""
        for job_id, (status, error) in list(self._unwritten.items()):
            if write_status(self._data, functools.partial(self._store.finish, job_id, status, error)):
                job_event(status.value, job_id, logging.WARNING if status is JobStatus.FAILED else logging.INFO,
                          error=error)
            del self._unwritten[job_id]

    def _enforce_cancels(self) -> None:
        now = time.monotonic()
        for slot in self._slots:
            asked = self._cancel_asked.get(slot.job_id) if slot.job_id else None
            if asked is not None and now - asked > self._cancel_grace_s and slot.process.is_alive():
                logger.warning("job %s ignored its cancel for %.1f s: killing its worker", slot.job_id, now - asked)
                slot.process.kill()

    def _assign_pending(self) -> None:
        idle = [s for s in self._slots if s.job_id is None and s.process.is_alive() and not s.retiring]
        while idle and self._pending:
            job_id = self._pending.popleft()
            try:
                job = self._store.get_job(job_id)
            except Exception:
                self._pending.appendleft(job_id)  # kept for the next tick
                raise
            if job is None or job.status is not JobStatus.QUEUED:
                continue
            slot = idle.pop(0)
            slot.job_id = job_id
            slot.inbox.put(job_id)


def _worker_entry(data_root: str, store: JobStore, job_function: str, slot: int, inbox: Any, outbox: Any,
                  memory_limit_mb: int = 0, heartbeat_s: float = 5.0, cancel_grace_s: float = 5.0) -> None:
    from service.runners.worker import worker_main

    worker_main(data_root, store, job_function, slot, inbox, outbox, memory_limit_mb, heartbeat_s, cancel_grace_s)
