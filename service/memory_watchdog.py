"""A job's memory (or an upload inspection's), watched from inside its process (Linux ``/proc/self``).

* The peak: the kernel's resident high-water mark (VmHWM) is reset when the job starts, so the
  peak read at its end is this job's, not the largest of every job the worker ever ran.
* The limit (``LIDARMAP_JOB_MEMORY_LIMIT_MB``): a watchdog thread samples the resident size
  (VmRSS) every 50 ms; past the limit it fails the job with the reason and kills its own worker
  (the runner replaces it), so a runaway job cannot take the machine down. A single huge
  allocation is stopped sooner by an address-space limit (RLIMIT_AS: the worker's size at the
  job's start plus the limit), which makes it fail with MemoryError, reported the same way.
"""

from __future__ import annotations

import os
import resource
import signal
import threading
from collections.abc import Callable
from pathlib import Path

MB = 1024 * 1024
POLL_S = 0.05


def _status_bytes(field: str) -> int:
    """A ``kB`` field of /proc/self/status in bytes (0 where /proc is missing)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def resident_bytes() -> int:
    return _status_bytes("VmRSS")


def reset_peak() -> bool:
    """Reset the resident high-water mark to the current size (Linux >= 4.0); False when impossible."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def limit_reason(limit_mb: int, resident: int | None = None) -> str:
    """The job's error when it passed the limit."""
    seen = "" if resident is None else f" (resident {resident / MB:.0f} MB)"
    return f"memory limit of {limit_mb} MB exceeded{seen}: the job was stopped"


class MemoryGuard:
    """Measures one job's peak resident memory and enforces ``limit_mb`` (0 = none) while it runs.

    ``on_exceeded(reason)`` is called (e.g. to fail the job in the store) before the worker process
    kills itself.
    """

    def __init__(self, limit_mb: int, on_exceeded: Callable[[str], None]):
        self.limit_mb = int(limit_mb or 0)
        self.on_exceeded = on_exceeded
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sampled_peak = 0
        self._old_as: tuple[int, int] | None = None

    def __enter__(self) -> MemoryGuard:
        reset_peak()
        self._sampled_peak = resident_bytes()
        if self.limit_mb:
            self._limit_address_space()
            self._thread = threading.Thread(target=self._watch, name="lidarmap-memory-guard", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)
        if self._old_as is not None:
            resource.setrlimit(resource.RLIMIT_AS, self._old_as)
            self._old_as = None

    def peak_bytes(self) -> int:
        """This job's peak resident memory so far [bytes]."""
        return max(_status_bytes("VmHWM"), self._sampled_peak, resident_bytes())

    def _limit_address_space(self) -> None:
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        wanted = _status_bytes("VmSize") + self.limit_mb * MB
        if hard != resource.RLIM_INFINITY:
            wanted = min(wanted, hard)
        if soft == resource.RLIM_INFINITY or wanted < soft:
            resource.setrlimit(resource.RLIMIT_AS, (wanted, hard))
            self._old_as = (soft, hard)

    def _watch(self) -> None:
        limit = self.limit_mb * MB
        while not self._stop.wait(POLL_S):
            resident = resident_bytes()
            self._sampled_peak = max(self._sampled_peak, resident)
            if resident > limit:
                try:
                    self.on_exceeded(limit_reason(self.limit_mb, resident))
                finally:
                    os.kill(os.getpid(), signal.SIGKILL)


def machine_memory_bytes() -> int:
    """Memory this process may use on this machine [bytes]: physical memory, or less where a cgroup
    (a container) limits it."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    try:
        text = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if text.isdigit():
            total = min(total, int(text))
    except OSError:
        pass
    return total


def default_limit_mb(workers: int, share: float = 0.8) -> int:
    """The default per-job limit [MB]: ``share`` of the machine's memory split between ``workers`` jobs."""
    return max(256, int(machine_memory_bytes() * share / max(1, workers) / MB))
