"""Child processes that die with the server: a worker or an inspection child whose parent (the API
process) is gone - killed with SIGKILL, crashed - kills itself within :data:`PARENT_POLL_S`.

A spawned child's parent is the API process; once that dies the child is re-parented (to init or
a subreaper) and ``os.getppid()`` changes. A thread in the child polls it. (Linux's parent-death
signal is not used: it fires when the *thread* that started the child exits, and workers are
respawned by the runner's supervisor thread, inspection children by request threads.) The
multiprocessing resource tracker ends by itself once the last process holding its pipe is gone.
"""

from __future__ import annotations

import os
import signal
import threading

PARENT_POLL_S = 0.5


def die_with_parent(poll_s: float = PARENT_POLL_S) -> threading.Thread:
    """Start the daemon thread that kills this process (SIGKILL) once its parent has gone."""
    parent = os.getppid()

    def watch() -> None:
        event = threading.Event()
        while not event.wait(poll_s):
            if os.getppid() != parent:
                os.kill(os.getpid(), signal.SIGKILL)

    thread = threading.Thread(target=watch, name="lidarmap-parent-watch", daemon=True)
    thread.start()
    return thread
