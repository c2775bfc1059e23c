"""A running job's heartbeat (:class:`Heartbeat`), written from a thread of the worker process that runs
it, whatever the runner: the runner's reaper fails a job whose heartbeat is older than ``worker_lost_s``
(its worker was stopped with SIGSTOP, hung in native code with the interpreter lock held, or its
machine died), and a job that ignores a cancel - or that is no longer this worker's, e.g. failed as
lost meanwhile - for ``cancel_grace_s`` has its process killed by this thread."""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Callable

from api_schemas.jobs import JobStatus
from service.jobs.context import JobContext, JobFunction
from service.storage.store import JobStore

logger = logging.getLogger("lidarmap.heartbeat")


class Heartbeat(threading.Thread):
    """Writes the job's heartbeat every ``every_s`` [s]; when the job should stop (cancel requested, or
    not running any more) and has not for ``cancel_grace_s`` [s], it marks the job cancelled (when it is
    still active) and kills this process."""

    def __init__(self, store: JobStore, job_id: str, every_s: float, cancel_grace_s: float,
                 kill: Callable[[], None] | None = None):
        super().__init__(name=f"lidarmap-heartbeat-{job_id[:8]}", daemon=True)
        self._store, self._job_id = store, job_id
        self._every_s, self._grace_s = every_s, cancel_grace_s
        self._kill = kill or (lambda: os.kill(os.getpid(), signal.SIGKILL))
        self._stopped = threading.Event()

    def stop(self) -> None:
        self._stopped.set()
        self.join(timeout=self._every_s + 1.0)

    def run(self) -> None:
        stop_asked_s: float | None = None
        failing = False
        while not self._stopped.wait(self._every_s):
            try:
                should_stop = self._store.heartbeat(self._job_id)
            except Exception:  # a locked or unreachable store, a full disk: try again at the next beat
                if not failing:  # once until a beat is written again
                    logger.exception("job %s: heartbeat failed (retried at each beat, logged once)", self._job_id)
                failing = True
                continue
            failing = False
            if not should_stop:
                continue
            stop_asked_s = stop_asked_s or time.monotonic()
            if time.monotonic() - stop_asked_s > self._grace_s and not self._stopped.is_set():
                logger.warning("job %s ignored its cancel for %.1f s: stopping its worker process", self._job_id,
                               time.monotonic() - stop_asked_s)
                self._store.finish(self._job_id, JobStatus.CANCELLED, "cancelled by request (worker stopped)")
                self._kill()
                return


def with_heartbeat(function: JobFunction, every_s: float, cancel_grace_s: float) -> JobFunction:
    """``function`` with a :class:`Heartbeat` thread beside it (started once the job is claimed)."""

    def run(ctx: JobContext) -> None:
        beat = Heartbeat(ctx.store, ctx.job_id, every_s, cancel_grace_s)
        beat.start()
        try:
            function(ctx)
        finally:
            beat.stop()

    return run
