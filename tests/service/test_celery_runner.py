"""Scale-out with Celery: a real Redis server and two real ``lidarmap worker`` processes behind the
unchanged HTTP API. Jobs map a simulated office drive and are checked against its ground truth.

Delivery semantics under test (service/runners/celery_runner.py): every job runs at most once (a duplicate
delivery is dropped by the store's claim), a worker lost mid-job fails its job with the reason -
at once when its pool process dies, after ``worker_lost_s`` without heartbeats when the whole
worker dies - and no job is ever left 'running'.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api_schemas.jobs import JobSource, JobStatus
from bench.throughput import free_port, redis_server
from service.api.app import create_app
from service.settings import Settings
from service.storage.store import JobStore

REPO_ROOT = Path(__file__).resolve().parents[2]
TERMINAL = {"succeeded", "failed", "cancelled"}
# WORKER_LOST_S leaves Celery time to notice a dead pool process itself (slow on a loaded 2-core machine)
# before the heartbeat reaper would fail the job with the other reason.
HEARTBEAT_S, WORKER_LOST_S, CANCEL_GRACE_S = 0.5, 8.0, 2.0
QUICK = {"particles": 5, "seed": 1, "resolution_m": 0.1, "snapshot_every_scans": 0}
# tens of seconds: long enough to kill or cancel mid-run however fast the engine gets (25 particles at
# 0.1 m finished its 200 scans before the cancel once the kernels got faster); every test stops it early
SLOW = {**QUICK, "particles": 100, "resolution_m": 0.05}


def _require(condition: bool, reason: str) -> None:
    if not condition:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(reason)
        pytest.skip(reason)


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory):
    """A throw-away redis-server on a free loopback port (no persistence)."""
    _require(shutil.which("redis-server") is not None, "redis-server not installed (Debian package redis-server): "
             "the Celery runner tests need a real Redis")
    _require(_importable("celery") and _importable("redis"), "celery/redis not installed: pip install '.[distributed]'")
    with redis_server(tmp_path_factory.mktemp("redis")) as url:
        yield url


def _importable(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


@dataclass
class Worker:
    name: str
    process: subprocess.Popen
    log_path: Path

    def owns(self, pid: int) -> bool:
        """Whether ``pid`` (a pool process) belongs to this worker (its own process group)."""
        try:
            return os.getpgid(pid) == self.process.pid
        except ProcessLookupError:
            return False

    def kill_all(self) -> None:
        """kill -9 the worker and its pool processes (a machine that vanishes)."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait(timeout=10)


@dataclass
class Cluster:
    client: TestClient
    store: JobStore
    workers: list[Worker]
    session_id: str
    ground_truth: object
    log_path: Path

    def post_job(self, config: dict) -> str:
        response = self.client.post(f"/v1/sessions/{self.session_id}/jobs", json=config)
        assert response.status_code == 202, response.text
        return response.json()["id"]

    def wait(self, job_id: str, statuses=TERMINAL, timeout_s: float = 40.0, condition=None) -> dict:
        deadline = time.monotonic() + timeout_s
        job: dict = {}
        while time.monotonic() < deadline:
            job = self.client.get(f"/v1/jobs/{job_id}").json()
            if job["status"] in statuses and (condition is None or condition(job)):
                return job
            time.sleep(0.05)
        raise AssertionError(f"job {job_id} did not reach {statuses} in {timeout_s} s: {job}\n{self.worker_logs()}")

    def worker_of(self, job_id: str) -> Worker:
        pid = self.store.get_job(job_id).worker_pid
        return next(w for w in self.workers if w.owns(pid))

    def worker_logs(self) -> str:
        return "\n".join(f"--- {w.name}\n" + w.log_path.read_text()[-3000:] for w in self.workers)


def _start_worker(name: str, env: dict, folder: Path) -> Worker:
    log_path = folder / f"{name}.log"
    with log_path.open("wb") as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "lidarmap.cli", "worker", "--concurrency", "1", "--hostname", f"{name}@test",
             "--loglevel", "info"], cwd=REPO_ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True)
    return Worker(name, process, log_path)


@pytest.fixture(scope="module")
def cluster(redis_url, tmp_path_factory):
    from slam_engine.simulation import simulate, write_simulated

    folder = tmp_path_factory.mktemp("celery")
    drive = simulate("office", seed=3, rig="carmen-robot", max_duration_s=40.0)
    log_path = write_simulated(drive, "carmen", folder / "sim")
    data_dir = folder / "data"
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "LIDARMAP_BROKER_URL": redis_url,
           "LIDARMAP_DATA_DIR": str(data_dir), "LIDARMAP_HEARTBEAT_S": str(HEARTBEAT_S),
           "LIDARMAP_WORKER_LOST_S": str(WORKER_LOST_S), "LIDARMAP_CANCEL_GRACE_S": str(CANCEL_GRACE_S),
           # pool processes live on after their jobs: worker_of() finds a job's worker by its pool process
           "LIDARMAP_WORKER_MAX_JOBS": "0"}
    workers = [_start_worker(f"w{i}", env, folder) for i in range(2)]
    settings = Settings(data_dir=data_dir, runner="celery", broker_url=redis_url, heartbeat_s=HEARTBEAT_S,
                        worker_lost_s=WORKER_LOST_S, cancel_grace_s=CANCEL_GRACE_S)
    try:
        with TestClient(create_app(settings)) as client:
            deadline = time.monotonic() + 40
            while client.get("/readyz").json()["workers"]["workers_alive"] < 2:
                assert time.monotonic() < deadline, "workers did not come up:\n" + "\n".join(
                    w.log_path.read_text()[-2000:] for w in workers)
                time.sleep(0.25)
            session_id = client.post("/v1/sessions", json={"name": "office"}).json()["id"]
            with log_path.open("rb") as f:
                upload = client.post(f"/v1/sessions/{session_id}/logs", files={"file": ("office.clf", f)})
            assert upload.status_code == 201, upload.text
            yield Cluster(client, client.app.state.store, workers, session_id, drive.ground_truth, log_path)
    finally:
        for worker in workers:
            if worker.process.poll() is None:
                os.killpg(worker.process.pid, signal.SIGTERM)
        for worker in workers:
            try:
                worker.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                worker.kill_all()


def _trajectory(client: TestClient, job_id: str):
    from slam_engine.model.result import Trajectory

    poses = client.get(f"/v1/jobs/{job_id}/trajectory").json()["poses"]
    return Trajectory(t_s=np.array([p["t_s"] for p in poses]),
                      poses=np.array([[p["x_m"], p["y_m"], p["theta_rad"]] for p in poses]))


def test_jobs_spread_over_both_workers_map_correctly_and_a_duplicate_delivery_is_dropped(cluster) -> None:
    from celery import Celery

    from service.runners.celery_runner import TASK_NAME
    from slam_engine.evaluation.metrics import absolute_trajectory_error

    job_ids = [cluster.post_job(QUICK) for _ in range(3)]
    jobs = [cluster.wait(job_id) for job_id in job_ids]
    assert [j["status"] for j in jobs] == ["succeeded"] * 3, jobs
    assert {cluster.worker_of(j).name for j in job_ids} == {"w0", "w1"}  # both workers took jobs

    # same log, same seed: the same trajectory whichever worker ran it, and close to the truth
    trajectories = [_trajectory(cluster.client, j) for j in job_ids]
    assert len(trajectories[0].t_s) == 200
    for other in trajectories[1:]:
        np.testing.assert_array_equal(other.poses, trajectories[0].poses)
    ate_m = absolute_trajectory_error(trajectories[0], cluster.ground_truth)
    assert ate_m < 0.1, f"ATE {ate_m:.3f} m"

    # a second delivery of a finished job's message is dropped by the claim, the job untouched
    before = cluster.store.get_job(job_ids[0])
    settings = cluster.client.app.state.settings
    sender = Celery(broker=settings.broker_url, backend=settings.broker_url, set_as_current=False)
    try:
        assert sender.send_task(TASK_NAME, args=[job_ids[0]], queue=settings.queue).get(timeout=20) == "skipped"
    finally:
        sender.close()
    assert cluster.store.get_job(job_ids[0]) == before


def test_cancel_a_running_and_a_queued_job(cluster) -> None:
    from celery import Celery

    running = [cluster.post_job(SLOW) for _ in range(2)]  # one per worker
    queued = cluster.post_job(QUICK)
    for job_id in running:
        cluster.wait(job_id, {"running"}, condition=lambda j: j["scans_done"] > 0)
    assert cluster.client.get(f"/v1/jobs/{queued}").json()["status"] == "queued"

    assert cluster.client.delete(f"/v1/jobs/{queued}").json()["status"] == "cancelled"  # at once
    for job_id in running:  # stopped by the job's own cancel check: no "(worker stopped)"
        cluster.client.delete(f"/v1/jobs/{job_id}")
        stopped = cluster.wait(job_id, timeout_s=60)
        assert stopped["status"] == "cancelled" and stopped["error"] == "cancelled by request"
        assert 0 < stopped["scans_done"] < 200
    # the cancelled job's message still reached a worker, which dropped it without running it
    settings = cluster.client.app.state.settings
    reader = Celery(broker=settings.broker_url, backend=settings.broker_url, set_as_current=False)
    try:
        assert reader.AsyncResult(queued).get(timeout=20) == "skipped"
    finally:
        reader.close()
    assert cluster.store.get_job(queued).started_at is None


def test_a_live_job_follows_its_stream_on_a_worker_and_maps_it_like_the_upload(cluster) -> None:
    """The live job runs in a pool process like any job: it maps the chunks as they come (waiting at
    a gap), finishes when the stream does, gives the upload's trajectory, and stops on cancel."""
    from service.storage.stream_log import calibration_from_log, messages_of_log
    from slam_engine.formats import load_log

    client = cluster.client
    loaded = load_log(cluster.log_path)
    messages = messages_of_log(loaded)
    chunks = [messages[i:i + 150] for i in range(0, len(messages), 150)]

    def live_job(session_id: str) -> str:
        live_params = {**QUICK, "live": True, "snapshot_every_scans": 25}  # live previews; the same map
        response = client.post(f"/v1/sessions/{session_id}/jobs", json=live_params)
        assert response.status_code == 202, response.text
        return response.json()["id"]

    def stream_session(name: str) -> str:
        body = {"name": name, "calibration": calibration_from_log(loaded)}
        return client.post("/v1/sessions", json=body).json()["id"]

    sid = stream_session("live")
    live = live_job(sid)
    assert client.post(f"/v1/sessions/{sid}/jobs", json={"live": True}).status_code == 409
    regular = cluster.post_job(QUICK)  # the upload of the same drive, on the other worker
    cluster.wait(live, {"running"})
    for seq in [0, 2, 1, *range(3, len(chunks))]:
        assert client.post(f"/v1/sessions/{sid}/chunks", json={"seq": seq, "messages": chunks[seq]}).status_code == 201
    caught_up = cluster.wait(live, {"running"}, condition=lambda j: j["scans_done"] == 200)
    assert caught_up["progress"] is None and "occupancy.png" in caught_up["products"]
    assert client.post(f"/v1/sessions/{sid}/chunks/finish").json()["last_seq"] == len(chunks) - 1
    done, upload = cluster.wait(live), cluster.wait(regular)
    assert done["status"] == upload["status"] == "succeeded", (done, upload)
    assert done["input"]["ended"] == "finished" and done["scans_total"] == 200
    np.testing.assert_array_equal(_trajectory(client, live).poses, _trajectory(client, regular).poses)

    waiting = live_job(stream_session("cancelled"))
    cluster.wait(waiting, {"running"})
    client.delete(f"/v1/jobs/{waiting}")
    stopped = cluster.wait(waiting, timeout_s=60)
    assert stopped["status"] == "cancelled" and stopped["error"] == "cancelled by request"


def test_killed_workers_fail_their_jobs_and_the_survivor_goes_on(cluster) -> None:
    jobs = [cluster.post_job(SLOW) for _ in range(2)]
    for job_id in jobs:
        cluster.wait(job_id, {"running"}, condition=lambda j: j["scans_done"] > 0)
    by_worker = {cluster.worker_of(job_id).name: job_id for job_id in jobs}
    assert set(by_worker) == {"w0", "w1"}
    w0, w1 = cluster.workers

    # w0's pool process is killed (OOM killer, a crash): w0 notices at once and fails the job
    os.kill(cluster.store.get_job(by_worker["w0"]).worker_pid, signal.SIGKILL)
    # w1 vanishes entirely (kill -9 of the worker and its pool): its heartbeats stop
    t_killed = time.monotonic()
    w1.kill_all()

    pool_lost = cluster.wait(by_worker["w0"], timeout_s=10)
    assert pool_lost["status"] == "failed"
    assert pool_lost["error"].startswith("worker lost: Worker exited prematurely: signal 9 (SIGKILL)"), pool_lost
    machine_lost = cluster.wait(by_worker["w1"], timeout_s=WORKER_LOST_S + 10)
    assert machine_lost["status"] == "failed"
    assert machine_lost["error"].startswith("worker lost: no heartbeat for"), machine_lost
    assert time.monotonic() - t_killed >= WORKER_LOST_S - 1.0  # not before its heartbeats were overdue

    # w0 replaced its pool process: the next job runs there and succeeds
    after = cluster.post_job(QUICK)
    assert cluster.wait(after)["status"] == "succeeded"
    assert cluster.worker_of(after) is w0
    assert cluster.store.jobs_with_status(JobStatus.QUEUED, JobStatus.RUNNING) == []


def test_heartbeat_stops_a_job_that_ignores_its_cancel(tmp_path) -> None:
    """The pool process's heartbeat thread: beats while the job runs; once a cancel has been ignored
    for the grace period it marks the job cancelled and kills its process (here: a stand-in)."""
    from service.runners.heartbeat import Heartbeat

    store = JobStore(tmp_path / "jobs.sqlite3")
    store.initialise()
    job_id = store.create_job("s", "", JobSource.LOG, None, {}).id
    assert store.mark_running(job_id, worker_pid=1)
    killed: list[float] = []
    beat = Heartbeat(store, job_id, every_s=0.05, cancel_grace_s=0.3, kill=lambda: killed.append(time.monotonic()))
    beat.start()
    time.sleep(0.3)
    first_beat = store.get_job(job_id).heartbeat_at
    time.sleep(0.2)
    assert store.get_job(job_id).heartbeat_at > first_beat and not killed
    asked = time.monotonic()
    store.request_cancel(job_id)
    beat.join(timeout=3)
    assert not beat.is_alive() and len(killed) == 1
    assert 0.3 <= killed[0] - asked < 1.0
    job = store.get_job(job_id)
    assert (job.status, job.error) == (JobStatus.CANCELLED, "cancelled by request (worker stopped)")


def test_reaper_fails_only_silent_running_jobs(tmp_path) -> None:
    store = JobStore(tmp_path / "jobs.sqlite3")
    store.initialise()
    silent, alive, queued = (store.create_job("s", "", JobSource.LOG, None, {}).id for _ in range(3))
    started = time.monotonic()
    for job_id in (silent, alive):
        assert store.mark_running(job_id, worker_pid=42)
    time.sleep(1.2)
    store.heartbeat(alive)
    assert store.fail_lost(silent_s=1.0) == [silent]
    silent_for_s = time.monotonic() - started
    job = store.get_job(silent)
    assert job.status is JobStatus.FAILED and job.cancel_requested
    reported = re.fullmatch(r"worker lost: no heartbeat for (\d+) s \(worker pid 42\).*", job.error)
    assert reported is not None, job.error
    assert 1 <= int(reported.group(1)) <= silent_for_s + 1
    assert [store.get_job(j).status for j in (alive, queued)] == ["running", "queued"]
    assert store.heartbeat(silent) is True  # a slow-but-alive worker is told to stop


def test_unreachable_broker_and_bad_settings_are_clear_errors(tmp_path) -> None:
    from pydantic import ValidationError

    from service.runners.celery_runner import CeleryRunner
    from service.storage.store import open_store

    _require(_importable("celery"), "celery not installed: pip install '.[distributed]'")
    with pytest.raises(RuntimeError, match=r"broker at redis://\*\*\*@127.0.0.1:\d+/0 is unreachable"):
        CeleryRunner(Settings(runner="celery", broker_url=f"redis://:secret@127.0.0.1:{free_port()}/0"), None, None)
    with pytest.raises(ValidationError, match="worker_lost_s .* must be at least twice heartbeat_s"):
        Settings(heartbeat_s=5, worker_lost_s=6)
    chosen = open_store(f"sqlite:///{tmp_path}/jobs.sqlite3", tmp_path / "default")
    assert chosen.backend.path == tmp_path / "jobs.sqlite3"
    with pytest.raises(ValueError, match="unsupported LIDARMAP_DATABASE_URL 'mysql://db/x'"):
        open_store("mysql://db/x", tmp_path / "default")
