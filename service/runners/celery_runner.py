"""The Celery runner: jobs go through a broker (Redis) to ``lidarmap worker`` processes on any
number of machines that reach the same job store and the same data folder.

Delivery semantics (what the tests check):

* **At most one run per job.** A worker claims the job in the store (an atomic queued -> running
  update, :meth:`JobStore.mark_running`) before any work. A delivery whose job is not 'queued' any
  more - a duplicate message, a redelivery after the broker's visibility timeout, a job cancelled
  while it waited - is dropped: the task returns ``"skipped"`` (:data:`SKIPPED`).
* **A lost worker fails its job; it is never retried.** A job that kills its worker (the OOM
  killer, a crash in native code) would kill the next one too, so the job is failed with the reason
  and the user may start it again:

  - the pool process running the job dies: the worker's main process notices at once and fails the
    job ``worker lost: Worker exited prematurely: signal 9 (SIGKILL) ...``;
  - the whole worker or its machine dies: the job's heartbeats (every ``heartbeat_s``) stop, and the
    API's reaper fails it after ``worker_lost_s``: ``worker lost: no heartbeat for 60 s ...``.

* **Fair dispatch.** Messages are acknowledged when the job ends (``acks_late``) and each pool
  process reserves one message at a time (prefetch 1), so a queued job never waits behind a long
  job on a busy worker while another worker is idle.
* **Cancel** is the store's flag, as with the local runner: the job stops at its next progress
  report; one that ignores the flag for ``cancel_grace_s`` is marked cancelled and its pool
  process is killed by its own heartbeat thread (the worker replaces the process).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from billiard.exceptions import WorkerLostError
from celery import Celery, signals

from api_schemas.jobs import JobStatus
from service.http_errors import LOW_SPACE_BYTES, Unavailable
from service.jobs.context import JobContext, JobFunction
from service.jobs.events import job_event
from service.runners.base import DEFAULT_JOB_FUNCTION, RunnerHealth
from service.runners.heartbeat import with_heartbeat
from service.runners.worker import execute_job, import_function
from service.storage.data_dir import DataDir
from service.storage.store import JobStore, open_store, safe_url

logger = logging.getLogger("lidarmap.celery")

TASK_NAME = "lidarmap.run_job"
SKIPPED = "skipped"  # the task's result for a delivery it dropped (the job was not queued any more)
VISIBILITY_TIMEOUT_S = 3600.0  # Redis: an unacknowledged message is redelivered after this (then dropped by the claim)
HEALTH_CACHE_S = 2.0


def make_celery(settings: Any, job_function: str | None = None, concurrency: int = 1) -> Celery:
    """The Celery app for ``settings`` with the job task registered (the API only sends by name;
    workers execute). ``job_function`` ("module:function") replaces the mapping job (tests);
    ``concurrency`` (a worker's pool processes) splits the default job memory limit."""
    app = Celery("lidarmap", broker=settings.broker_url, backend=settings.broker_url, set_as_current=False)
    app.conf.update(
        task_acks_late=True,
        task_reject_on_worker_lost=False,  # a lost worker fails the job (see the module docstring)
        worker_prefetch_multiplier=1,
        task_default_queue=settings.queue,
        task_serializer="json", result_serializer="json", accept_content=["json"],
        result_expires=24 * 3600,
        broker_transport_options={"visibility_timeout": VISIBILITY_TIMEOUT_S},
        broker_connection_retry_on_startup=True,
        worker_hijack_root_logger=False,
        worker_redirect_stdouts=False,
        worker_max_tasks_per_child=settings.worker_max_jobs or None,  # a fresh pool process: the memory back
        lidarmap_data_dir=str(settings.data_dir),
        lidarmap_database_url=settings.database_url,
        lidarmap_job_function=job_function or DEFAULT_JOB_FUNCTION,
        lidarmap_heartbeat_s=settings.heartbeat_s,
        lidarmap_cancel_grace_s=settings.cancel_grace_s,
        lidarmap_job_memory_limit_mb=settings.job_memory_limit(concurrency),
    )

    @app.task(name=TASK_NAME)
    def run_job(job_id: str) -> str:
        """Claim and run one job; returns its final status, or "skipped" for a dropped delivery."""
        return run_job_in_worker(job_id, app.conf)

    def on_failure(sender: Any = None, task_id: str | None = None, exception: BaseException | None = None,
                   args: Any = None, **_: Any) -> None:
        if isinstance(exception, WorkerLostError) and args:
            job_id = str(args[0])
            reason = f"worker lost: {exception}".strip()
            if _store_of(app.conf).finish(job_id, JobStatus.FAILED, reason):
                job_event(JobStatus.FAILED.value, job_id, logging.WARNING, error=reason)

    signals.task_failure.connect(on_failure, sender=run_job, weak=False)
    return app


def _store_of(conf: Any) -> JobStore:
    data = DataDir(conf.lidarmap_data_dir)
    return open_store(conf.lidarmap_database_url, data.database)


_functions: dict[str, JobFunction] = {}


def run_job_in_worker(job_id: str, conf: Any) -> str:
    """Inside a worker's pool process: the same claim, status transitions and job function as the
    local runner (:func:`service.runners.worker.execute_job`), plus a heartbeat thread while it runs."""
    data = DataDir(conf.lidarmap_data_dir)
    store = _store_of(conf)
    name = conf.lidarmap_job_function
    if name not in _functions:
        try:
            _functions[name] = import_function(name)
        except Exception as exc:  # fail the job with the reason instead of crashing the task
            reason = f"worker cannot load the job function {name!r}: {type(exc).__name__}: {exc}"

            def _broken(ctx: JobContext, reason: str = reason) -> None:
                raise RuntimeError(reason)

            _functions[name] = _broken
    function = with_heartbeat(_functions[name], conf.lidarmap_heartbeat_s, conf.lidarmap_cancel_grace_s)
    status = execute_job(job_id, store, data, function, conf.lidarmap_job_memory_limit_mb)
    if status is None:
        logger.info("job %s: not queued any more (duplicate delivery, or cancelled): dropped", job_id)
    return SKIPPED if status is None else status.value


class CeleryRunner:
    """The API side: sends job ids to the broker, reaps jobs of lost workers, reports worker health."""

    def __init__(self, settings: Any, data: DataDir, store: JobStore):
        self._settings = settings
        self._store = store
        self._data = data
        self._app = make_celery(settings)
        try:
            with self._app.connection_for_write() as conn:
                conn.ensure_connection(max_retries=3, interval_start=0.2, interval_step=0.4, interval_max=1.0)
        except Exception as exc:
            raise RuntimeError(f"the Celery broker at {safe_url(settings.broker_url)} is unreachable: {exc}") from exc
        self._stopping = threading.Event()
        self._health: tuple[float, RunnerHealth] | None = None
        self._reaper = threading.Thread(target=self._reap_loop, name="lidarmap-reaper", daemon=True)
        self._reaper.start()

    # ---- JobRunner ------------------------------------------------------------------------------

    def submit(self, job_id: str) -> None:
        try:
            self._app.send_task(TASK_NAME, args=[job_id], task_id=job_id, queue=self._settings.queue)
        except Exception as exc:
            reason = f"could not queue the job: the broker at {safe_url(self._settings.broker_url)} is unreachable"
            self._store.finish(job_id, JobStatus.FAILED, reason)
            raise Unavailable(reason, {"job_id": job_id}) from exc

    def cancel(self, job_id: str) -> None:
        """Nothing to send: the store's flag is the request, and the job's worker enforces it."""

    def shutdown(self) -> None:
        """Stop the reaper; workers and their jobs go on (they do not belong to this process)."""
        self._stopping.set()
        self._reaper.join(timeout=5.0)
        self._app.close()

    def health(self) -> RunnerHealth:
        """Pool processes of the workers that answer a ping within a second (cached briefly)."""
        now = time.monotonic()
        if self._health is not None and now - self._health[0] < HEALTH_CACHE_S:
            return self._health[1]
        try:
            stats = self._app.control.inspect(timeout=1.0).stats() or {}
        except Exception:
            logger.exception("cannot reach the Celery workers")
            stats = {}
        processes = sum(int(s.get("pool", {}).get("max-concurrency", 0)) for s in stats.values())
        busy = len(self._store.jobs_with_status(JobStatus.RUNNING))
        queued = len(self._store.jobs_with_status(JobStatus.QUEUED))
        health = RunnerHealth("celery", processes, processes, busy, queued)
        self._health = (now, health)
        return health

    # ---- reaper ---------------------------------------------------------------------------------

    def _reap_loop(self) -> None:
        while not self._stopping.wait(self._settings.heartbeat_s):
            try:
                full = self._data.free_bytes() < LOW_SPACE_BYTES  # heartbeats that could not be written
                for job_id in self._store.fail_lost(self._settings.worker_lost_s, disk_full=full):
                    job_event(JobStatus.FAILED.value, job_id, logging.WARNING,
                              error=f"{'disk full' if full else 'worker lost'}: no heartbeat for "
                                    f"{self._settings.worker_lost_s:.0f} s")
            except Exception:  # the reaper must survive a locked database
                logger.exception("reaper pass failed")
