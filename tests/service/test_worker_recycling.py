"""An idle worker does not keep what its jobs left behind: after max_jobs_per_worker jobs (default 1)
the local runner replaces the worker process by a fresh one. Resident memory is measured on the worker
processes themselves (the kernel's VmRSS)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.service.service_helpers import service_client, streaming_session, wait_for
from tests.service.service_job_functions import HOARD_MB

FUNCS = "tests.service.service_job_functions"


def rss_mb(pid: int) -> float:
    """Resident memory of process ``pid`` [MB] (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for pid {pid}")


def worker_rss_mb(client) -> dict[int, float]:
    """pid -> resident memory [MB] of the runner's live worker processes, once none is busy or starting."""
    runner = client.app.state.runner
    deadline = time.monotonic() + 60
    while True:
        health = runner.health()
        settled = health.busy == 0 and health.workers_alive == health.workers_total
        if settled and not any(slot.retiring for slot in runner._slots):  # (the runner's own view)
            pids = [slot.process.pid for slot in runner._slots]
            time.sleep(1.0)  # a fresh worker finishes its imports
            return {pid: rss_mb(pid) for pid in pids}
        assert time.monotonic() < deadline, health
        time.sleep(0.1)


@pytest.mark.parametrize("max_jobs", [1, 0])
def test_an_idle_worker_gives_back_what_its_job_left(tmp_path, max_jobs: int) -> None:
    with service_client(tmp_path, job_function=f"{FUNCS}:hoarding", workers=1, worker_max_jobs=max_jobs) as client:
        sid = streaming_session(client)
        store = client.app.state.store
        ran_on = []
        for _ in range(2):
            job = client.post(f"/v1/sessions/{sid}/jobs", json={}).json()
            assert wait_for(client, job["id"])["status"] == "succeeded"
            ran_on.append(store.get_job(job["id"]).worker_pid)
            idle = worker_rss_mb(client)
            if max_jobs == 1:  # a fresh worker, without the job's memory
                assert ran_on[-1] not in idle and max(idle.values()) < HOARD_MB * 0.6, idle
            else:  # one worker for every job: it keeps what they left (what the recycling is for)
                assert list(idle) == [ran_on[0]] and max(idle.values()) > HOARD_MB * len(ran_on), idle
        assert (ran_on[0] != ran_on[1]) == (max_jobs == 1)
