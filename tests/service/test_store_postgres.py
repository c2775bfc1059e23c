"""The job store on both backends: SQLite (the default) and a real PostgreSQL server started for
these tests (Debian's binaries in /usr/lib/postgresql/<version>/bin; package ``postgresql``).

Every behaviour test runs against both: sessions, logs, chunks, jobs, progress, cancel flags, the
atomic queued -> running claim under concurrent claimers, heartbeats and lost workers, a restart.
Then the whole service on PostgreSQL: an upload mapped by a local worker process, whose rows land in
PostgreSQL (not in a SQLite file), and errors that never show the database password.
"""

from __future__ import annotations

import os
import sqlite3
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient
from postgres_server import PG_USER, free_port
from service_helpers import store_on_backend

import service.storage.job_records as job_records
import service.storage.log_records as log_records
from api_schemas.jobs import JobSource, JobStatus
from service.api.app import create_app
from service.settings import Settings
from service.storage.rows import JobRow, LogRow
from service.storage.store import JobStore, PostgresBackend, StoreUnavailable, open_store, safe_url

QUICK = {"particles": 5, "seed": 1, "resolution_m": 0.1, "snapshot_every_scans": 0}


@pytest.fixture(params=["sqlite", "postgres"])
def store(request, tmp_path) -> Iterator[JobStore]:
    """An initialised, empty store on each backend (its pooled connections closed afterwards)."""
    store = store_on_backend(request, tmp_path)
    store.initialise()
    yield store
    store.close()


class FakeClock:
    """Stands in for the ``time`` module inside a module of service.storage (log_records, job_records)."""

    def __init__(self, now: float):
        self.now = now

    def time(self) -> float:
        return self.now


# ---- behaviour, on both backends ----------------------------------------------------------------


def test_sessions_logs_and_chunks(store, monkeypatch) -> None:
    calibration = {"lidar": {"num_beams": 2}}
    session = store.create_session("alice", "drive 1", "turtlebot", calibration, None)
    other = store.create_session("bob", "drive 2", None, None, {"lat": 1.0})
    assert session.calibration == calibration and session.geo is None
    assert (session.logs, session.chunks, session.jobs) == (0, 0, 0)
    assert abs(session.created_at - time.time()) < 1.0  # a double (a 4-byte REAL: 128 s steps)
    assert store.get_session(session.id, "bob") is None
    assert store.get_session(other.id, "bob").geo == {"lat": 1.0}
    for i in range(3):
        store.create_session("alice", f"more {i}", None, None, None)
    page, count = store.list_sessions("alice", limit=2, offset=0)
    assert count == 4 and [s.name for s in page] == ["more 2", "more 1"]

    # two uploads within one clock tick: the second is still the newest
    monkeypatch.setattr(log_records, "time", FakeClock(1_700_000_000.123456))
    big = 5 * 1024**3  # beyond a 32-bit integer
    first = store.add_log("log-1", session.id, "a.clf", big, "aa", False, {"format": "carmen"}, "uploads/1/log")
    store.add_log("log-2", session.id, "b.zip", 10, "bb", True, {"format": "thor"}, "uploads/2/tree")
    assert first == LogRow(id="log-1", session_id=session.id, filename="a.clf", size_bytes=big, sha256="aa",
                           archive=False, summary={"format": "carmen"}, stored_path="uploads/1/log",
                           created_at=1_700_000_000.123456)
    assert [log.id for log in store.list_logs(session.id)] == ["log-2", "log-1"]
    assert store.get_log("log-1", session.id) == first
    assert store.get_log("log-1", other.id) is None
    assert store.get_log("log-2", session.id).archive is True

    new = store.put_chunk(session.id, 1, "h1", 10, 0.5, 0.9)
    assert not new.duplicate and not new.conflict
    store.put_chunk(session.id, 0, "h0", 5, 0.0, 0.4)
    retry = store.put_chunk(session.id, 1, "h1", 10, 0.5, 0.9)
    assert retry.duplicate and not retry.conflict and retry.row.created_at == new.row.created_at
    clash = store.put_chunk(session.id, 1, "other", 3, 0.0, 0.1)
    assert clash.conflict and clash.row.sha256 == "h1"
    assert [(c.seq, c.messages, c.t_last_s) for c in store.chunk_rows(session.id)] == [
        (0, 5, 0.4), (1, 10, 0.9)]

    job = store.create_job(session.id, "alice", JobSource.LOG, "log-2", {"particles": 30})
    counts = store.get_session(session.id, "alice")
    assert (counts.logs, counts.chunks, counts.jobs) == (2, 2, 1)
    assert store.delete_session(session.id) == [job.id]
    assert store.get_session(session.id, "alice") is None and store.get_job(job.id) is None
    assert store.list_logs(session.id) == [] and store.chunk_rows(session.id) == []
    assert store.get_session(other.id, "bob") is not None


def test_job_lifecycle_progress_and_cancel_flags(store) -> None:
    sid = store.create_session("", "s", None, None, None).id
    job = store.create_job(sid, "", JobSource.STREAM, None, {"particles": 10})
    assert (job.status, job.progress, job.scans_done, job.config) == (JobStatus.QUEUED, 0.0, 0, {"particles": 10})
    assert isinstance(job, JobRow) and type(job.status) is JobStatus and job.source is JobSource.STREAM
    assert job.products == {} and job.input is None and job.cancel_requested is False
    assert store.mark_running(job.id, worker_pid=4321) is True
    assert store.mark_running(job.id, worker_pid=999) is False  # already claimed
    store.set_input(job.id, {"format": "carmen", "scans": 200})
    assert store.update_progress(job.id, 50, 200) is False
    running = store.get_job(job.id)
    assert (running.status, running.worker_pid, running.progress) == ("running", 4321, 0.25)
    assert running.input == {"format": "carmen", "scans": 200}
    assert running.heartbeat_at >= running.started_at >= running.created_at
    store.set_products(job.id, {"occupancy.png": "occupancy.png"})
    assert store.finish(job.id, JobStatus.SUCCEEDED) is True
    assert store.finish(job.id, JobStatus.FAILED, "late") is False  # first writer wins
    done = store.get_job(job.id)
    assert (done.status, done.progress, done.error) == ("succeeded", 1.0, None)
    assert done.products == {"occupancy.png": "occupancy.png"}

    # cancel: a queued job at once (and it can no longer be claimed), a running one by its flag
    queued = store.create_job(sid, "", JobSource.STREAM, None, {}).id
    active = store.create_job(sid, "", JobSource.STREAM, None, {}).id
    assert store.mark_running(active, worker_pid=1)
    assert store.request_cancel(queued) == "cancelled" and store.mark_running(queued, 1) is False
    assert store.get_job(queued).error == "cancelled by request"
    assert store.cancel_requested(active) is False
    assert store.request_cancel(active) == "running"
    assert store.cancel_requested(active) is True and store.update_progress(active, 3, 10) is True
    assert store.finish(active, JobStatus.CANCELLED, "cancelled by request") is True
    assert store.request_cancel(active) == "cancelled" and store.request_cancel("no-such-job") is None
    assert store.cancel_requested("no-such-job") is True

    assert store.get_job(job.id, owner="someone else") is None
    listed, count = store.list_jobs("", sid, JobStatus.CANCELLED, limit=10, offset=0)
    assert count == 2 and {j.id for j in listed} == {queued, active}
    assert store.list_jobs("", None, None, limit=1, offset=0)[1] == 3
    later = store.create_job(sid, "", JobSource.STREAM, None, {}).id
    assert store.jobs_with_status(JobStatus.QUEUED, JobStatus.RUNNING) == [later]


def test_the_claim_is_atomic_under_concurrent_claimers(store) -> None:
    """Four claimers race for each of 15 queued jobs at the same instant: exactly one wins each."""
    sid = store.create_session("", "s", None, None, None).id
    jobs = [store.create_job(sid, "", JobSource.LOG, None, {}).id for _ in range(15)]
    claimers = 4
    barrier = threading.Barrier(claimers)
    wins: dict[int, list[str]] = {pid: [] for pid in range(1, claimers + 1)}
    errors: list[BaseException] = []

    def claim_all(pid: int) -> None:
        try:
            for job_id in jobs:
                barrier.wait(timeout=30)
                if store.mark_running(job_id, worker_pid=pid):
                    wins[pid].append(job_id)
        except BaseException as exc:  # reported below
            errors.append(exc)
            barrier.abort()

    threads = [threading.Thread(target=claim_all, args=(pid,)) for pid in wins]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert not errors, errors
    assert sorted(j for won in wins.values() for j in won) == sorted(jobs)  # each job claimed exactly once
    for pid, won in wins.items():
        assert all(store.get_job(j).worker_pid == pid for j in won)
    assert store.jobs_with_status(JobStatus.RUNNING) == jobs


def test_concurrent_chunks_with_one_seq_keep_the_first(store) -> None:
    sid = store.create_session("", "s", None, None, None).id
    barrier = threading.Barrier(4)
    outcomes = {}

    errors: list[BaseException] = []

    def put(sha: str) -> None:
        barrier.wait(timeout=30)
        try:
            outcomes[sha] = store.put_chunk(sid, 7, sha, 1, 0.0, 1.0)
        except BaseException as exc:  # e.g. a unique violation from a check-then-insert
            errors.append(exc)

    threads = [threading.Thread(target=put, args=(f"hash-{i}",)) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert not errors, errors
    assert len(outcomes) == 4
    winners = [sha for sha, o in outcomes.items() if not o.conflict]
    assert len(winners) == 1 and not outcomes[winners[0]].duplicate
    assert all(o.row.sha256 == winners[0] for o in outcomes.values())
    assert [c.sha256 for c in store.chunk_rows(sid)] == winners


def test_one_live_job_per_session_under_concurrent_creators(store) -> None:
    sid = store.create_session("", "s", None, None, None).id
    other = store.create_session("", "t", None, None, None).id
    store.create_job(sid, "", JobSource.STREAM, None, {"live": False})  # a regular job does not count
    barrier = threading.Barrier(4)
    outcomes: list[tuple] = []
    errors: list[BaseException] = []

    def create() -> None:
        try:
            barrier.wait(timeout=30)
            outcomes.append(store.create_live_job(sid, "", {"live": True}))
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=create) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert not errors, errors
    created = [row for row, _ in outcomes if row is not None]
    assert len(created) == 1 and created[0].source == "stream" and created[0].config == {"live": True}
    assert all(active.id == created[0].id for row, active in outcomes if row is None)
    assert store.create_live_job(other, "", {"live": True})[0] is not None  # another session: its own
    assert store.finish(created[0].id, JobStatus.CANCELLED)
    assert store.create_live_job(sid, "", {"live": True})[0] is not None  # the first one ended


def test_the_stream_end_and_chunks_beyond_it(store) -> None:
    sid = store.create_session("", "s", None, None, None).id
    assert store.stream_end(sid) is None and store.finish_stream(sid, None).conflict
    for seq in (0, 2):
        store.put_chunk(sid, seq, f"h{seq}", 1, seq, seq + 0.5)
    assert "beyond last_seq 1" in store.finish_stream(sid, 1).conflict
    assert store.finish_stream(sid, None).last_seq == 2 and store.stream_end(sid) == 2
    assert store.finish_stream(sid, 2).conflict is None  # again: the same end
    assert store.finish_stream(sid, 3).conflict == "the stream was already finished at seq 2"
    assert store.stream_figures(sid).last_seq == 2
    assert store.put_chunk(sid, 3, "h3", 1, 3.0, 3.5).beyond_end == 2
    assert store.put_chunk(sid, 1, "h1", 1, 1.0, 1.5).row.seq == 1  # below the end: welcome
    assert store.put_chunk(sid, 2, "h2", 1, 2.0, 2.5).duplicate
    store.delete_session(sid)
    assert store.stream_end(sid) is None

    # a finish racing a chunk beyond it: one of the two is refused, never both stored
    for round_no in range(6):
        race = store.create_session("", f"race {round_no}", None, None, None).id
        store.put_chunk(race, 0, "h0", 1, 0.0, 0.5)
        barrier = threading.Barrier(2)
        result: dict[str, object] = {}

        def finish(race: str = race, barrier: threading.Barrier = barrier, result: dict = result) -> None:
            barrier.wait(timeout=30)
            result["finish"] = store.finish_stream(race, 0)

        def chunk(race: str = race, barrier: threading.Barrier = barrier, result: dict = result) -> None:
            barrier.wait(timeout=30)
            result["chunk"] = store.put_chunk(race, 1, "h1", 1, 1.0, 1.5)

        threads = [threading.Thread(target=finish), threading.Thread(target=chunk)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
        finished = result["finish"].conflict is None
        stored = result["chunk"].beyond_end is None
        assert finished != stored, result
        assert [c.seq for c in store.chunk_rows(race)] == ([0] if finished else [0, 1])


def test_heartbeats_and_lost_workers(store, monkeypatch) -> None:
    clock = FakeClock(1_000.0)
    monkeypatch.setattr(job_records, "time", clock)
    sid = store.create_session("", "s", None, None, None).id
    beating, silent, queued = (store.create_job(sid, "", JobSource.LOG, None, {}).id for _ in range(3))
    assert store.mark_running(beating, worker_pid=11) and store.mark_running(silent, worker_pid=22)
    clock.now = 1_030.0
    assert store.heartbeat(beating) is False
    assert store.fail_lost(silent_s=60.0) == []
    clock.now = 1_065.0
    assert store.fail_lost(silent_s=60.0) == [silent]
    lost = store.get_job(silent)
    assert (lost.status, lost.cancel_requested, lost.finished_at) == ("failed", True, 1_065.0)
    assert lost.error == "worker lost: no heartbeat for 65 s (worker pid 22): its process or machine stopped"
    assert store.heartbeat(silent) is True  # a worker that was only stalled is told to stop
    assert store.update_progress(silent, 5, 10) is True
    assert store.finish(silent, JobStatus.SUCCEEDED) is False
    assert store.get_job(beating).heartbeat_at == 1_030.0 and store.get_job(beating).status == "running"
    assert store.get_job(queued).status == "queued"
    assert store.fail_lost(silent_s=60.0) == []  # failed once
    store.request_cancel(beating)
    assert store.heartbeat(beating) is True


def test_a_job_whose_heartbeats_met_a_full_disk_fails_saying_so(store, monkeypatch) -> None:
    clock = FakeClock(1_000.0)
    monkeypatch.setattr(job_records, "time", clock)
    sid = store.create_session("", "s", None, None, None).id
    job = store.create_job(sid, "", JobSource.LOG, None, {}).id
    assert store.mark_running(job, worker_pid=33)
    clock.now = 1_070.0
    assert store.fail_lost(silent_s=60.0, disk_full=True) == [job]  # the runner saw the data folder full
    assert store.get_job(job).error == ("disk full: the service's data folder has no space left; no heartbeat "
                                        "for 70 s (worker pid 33) could be written")


def test_restart_keeps_rows_and_fails_interrupted_jobs(store) -> None:
    sid = store.create_session("", "s", None, None, None).id
    done, interrupted, waiting = (store.create_job(sid, "", JobSource.LOG, None, {}).id for _ in range(3))
    for job_id in (done, interrupted):
        assert store.mark_running(job_id, worker_pid=7)
    store.finish(done, JobStatus.SUCCEEDED)

    restarted = JobStore(store.backend)  # a new process on the same database
    restarted.initialise()  # idempotent: nothing dropped
    assert restarted.ping() is True
    assert restarted.get_session(sid, "").jobs == 3
    assert restarted.fail_interrupted() == [interrupted]
    job = restarted.get_job(interrupted)
    assert job.status == "failed" and job.error.startswith("interrupted: the service stopped")
    assert restarted.get_job(done).status == "succeeded"
    assert restarted.jobs_with_status(JobStatus.QUEUED) == [waiting]
    assert restarted.fail_interrupted() == []


def test_a_sqlite_file_from_before_upload_numbers_is_upgraded(tmp_path) -> None:
    path = tmp_path / "old.sqlite3"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE logs (id TEXT PRIMARY KEY, session_id TEXT NOT NULL, filename TEXT NOT NULL, "
                     "size_bytes INTEGER NOT NULL, sha256 TEXT NOT NULL, archive INTEGER NOT NULL, format TEXT "
                     "NOT NULL, summary_json TEXT NOT NULL, stored_path TEXT NOT NULL, created_at REAL NOT NULL)")
        conn.execute("INSERT INTO logs VALUES ('old', 's', 'a.clf', 1, 'x', 0, 'carmen', '{}', 'p', 2e9)")
    conn.close()
    store = JobStore(path)
    store.initialise()
    sid = store.create_session("owner", "drive", None, None, None).id
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE logs SET session_id = ? WHERE id = 'old'", (sid,))
    conn.close()
    store.add_log("new", sid, "b.clf", 1, "y", False, {}, "q")  # created_at now < the old row's 2e9
    assert [log.id for log in store.list_logs(sid)] == ["new", "old"]
    assert store.add_log("gone", "no-such-session", "c.clf", 1, "z", False, {}, "r") is None


# ---- PostgreSQL: URLs, unreachable servers, the whole service -----------------------------------


def test_database_urls_and_passwords_never_shown(postgres, tmp_path) -> None:
    assert safe_url("postgresql://me:s3cr%40t@db:5432/x?sslmode=require&password=two") == \
        "postgresql://me:***@db:5432/x?sslmode=require&password=***"
    assert isinstance(open_store("postgres://me@db/x", tmp_path).backend, PostgresBackend)
    with pytest.raises(ValueError, match=r"unsupported LIDARMAP_DATABASE_URL 'mysql://me:\*\*\*@db/x'") as info:
        open_store("mysql://me:hunter2@db/x", tmp_path)
    assert "hunter2" not in str(info.value)

    wrong = open_store(postgres.url("postgres", password="wrong-password-123"), tmp_path)
    assert "wrong-password-123" not in repr(wrong)
    with pytest.raises(StoreUnavailable, match="password authentication failed") as info:
        wrong.initialise()
    assert f"postgresql://{PG_USER}:***@127.0.0.1:{postgres.port}/postgres" in info.value.message
    assert "wrong-password-123" not in info.value.message and info.value.__suppress_context__
    assert info.value.status_code == 503 and wrong.ping() is False

    down = open_store(f"postgresql://{PG_USER}:{postgres.password}@127.0.0.1:{free_port()}/x", tmp_path)
    with pytest.raises(StoreUnavailable, match="is unavailable: connection failed") as info:
        down.get_job("x")
    assert postgres.password not in info.value.message and down.ping() is False
    wrong.close()
    down.close()


def test_postgres_store_borrows_pooled_connections(postgres, tmp_path) -> None:
    """Transactions reuse a few pooled connections (not one connection each); a pickled store (as
    sent to a worker process) carries no engine and makes its own; close() ends the connections."""
    import pickle
    from concurrent.futures import ThreadPoolExecutor

    from sqlalchemy import event

    from service.storage.store import POSTGRES_POOL_MAX_CONNECTIONS

    store = open_store(postgres.new_database(), tmp_path / "unused.sqlite3")
    store.initialise()
    session = store.create_session("alice", "pooled", None, None, None)
    engine = store.backend.engine()
    opened, lent = [], []
    event.listen(engine, "connect", lambda *_: opened.append(1))
    event.listen(engine, "checkout", lambda *_: lent.append(1))
    before = engine.pool.checkedin()
    with ThreadPoolExecutor(max_workers=8) as threads:
        found = list(threads.map(lambda _: store.get_session(session.id, "alice"), range(200)))
    assert all(row.name == "pooled" for row in found)
    assert len(lent) == 200
    assert 1 <= before + len(opened) == engine.pool.checkedin() <= POSTGRES_POOL_MAX_CONNECTIONS  # opened, ever

    copy = pickle.loads(pickle.dumps(store))
    assert copy.backend._engine is None and copy.get_session(session.id, "alice").name == "pooled"
    assert copy.backend._engine is not engine
    store.close()
    copy.close()
    assert store.backend._engine is None and store.ping() is True  # a closed store opens a new pool on use
    store.close()


def test_the_service_on_postgres_maps_an_upload(postgres, tmp_path, caplog) -> None:
    """API + a local worker process on PostgreSQL: a simulated office drive mapped end to end."""
    import psycopg

    from slam_engine.evaluation.metrics import absolute_trajectory_error
    from slam_engine.model.result import Trajectory
    from slam_engine.simulation import simulate, write_simulated

    drive = simulate("office", seed=3, rig="carmen-robot", max_duration_s=20.0)
    log_path = write_simulated(drive, "carmen", tmp_path / "sim")
    url, data_dir = postgres.new_database(), tmp_path / "data"
    with TestClient(create_app(Settings(data_dir=data_dir, database_url=url, workers=1))) as client:
        sid = client.post("/v1/sessions", json={"name": "office"}).json()["id"]
        with log_path.open("rb") as f:
            assert client.post(f"/v1/sessions/{sid}/logs", files={"file": ("office.clf", f)}).status_code == 201
        job_id = client.post(f"/v1/sessions/{sid}/jobs", json=QUICK).json()["id"]
        deadline, job = time.monotonic() + 60, {}
        while time.monotonic() < deadline and job.get("status") not in ("succeeded", "failed", "cancelled"):
            time.sleep(0.1)
            job = client.get(f"/v1/jobs/{job_id}").json()
        assert job["status"] == "succeeded", job
        assert job["scans_done"] == job["scans_total"] == len(drive.ground_truth.t_s) and job["progress"] == 1.0
        poses = client.get(f"/v1/jobs/{job_id}/trajectory").json()["poses"]
        trajectory = Trajectory(t_s=np.array([p["t_s"] for p in poses]),
                                poses=np.array([[p["x_m"], p["y_m"], p["theta_rad"]] for p in poses]))
        ate_m = absolute_trajectory_error(trajectory, drive.ground_truth)
        assert ate_m < 0.1, f"ATE {ate_m:.3f} m"
        assert client.get("/readyz").json()["storage"]["database_ok"] is True

        # the database goes away (here: a wrong password): 503 without the password
        client.app.state.store = open_store(postgres.url(url.rsplit("/", 1)[1], password="not-it-42"), tmp_path)
        response = client.get(f"/v1/jobs/{job_id}")
        assert response.status_code == 503 and response.json()["error"]["code"] == "unavailable"
        assert "not-it-42" not in response.text and postgres.password not in response.text
        client.app.state.store.close()

    # the worker process wrote PostgreSQL, not a SQLite file in the data folder
    assert not (data_dir / "lidarmap.sqlite3").exists()
    with psycopg.connect(url) as conn:
        row = conn.execute("SELECT status, worker_pid, scans_done FROM jobs WHERE id = %s", (job_id,)).fetchone()
    assert row[0] == "succeeded" and row[1] != os.getpid() and row[2] == len(drive.ground_truth.t_s)
    assert postgres.password not in caplog.text
