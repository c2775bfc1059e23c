"""The job lifecycle log (service.jobs.events): one key=value line per event, as the worker writes it
around a job (started, then succeeded / failed / cancelled with the duration) and as the API writes it
(created; a queued job cancelled). The whole sequence of a real job through `lidarmap serve`:
tests/service/test_serve_process.py."""

from __future__ import annotations

import logging
import shlex
from pathlib import Path

import pytest

from api_schemas.jobs import JobSource, JobStatus
from service.jobs.events import job_event
from service.runners.worker import execute_job
from service.storage.data_dir import DataDir
from service.storage.store import JobStore
from tests.service.service_helpers import new_session, service_client
from tests.service.service_job_functions import bad_log, counting

FUNCS = "tests.service.service_job_functions"


def events(caplog: pytest.LogCaptureFixture) -> list[dict[str, str]]:
    lines = [r.getMessage() for r in caplog.records if r.name == "lidarmap.jobs"]
    return [dict(pair.split("=", 1) for pair in shlex.split(line.removeprefix("job "))) for line in lines]


def test_a_line_quotes_values_with_spaces_and_leaves_out_none(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "lidarmap.jobs")
    job_event("stage", "j1", stage="closing loops", progress=0.70012, error=None, note='say "hi"')
    assert caplog.records[-1].getMessage() == 'job event=stage job=j1 stage="closing loops" progress=0.7 ' \
                                              'note="say \\"hi\\""'
    assert events(caplog) == [{"event": "stage", "job": "j1", "stage": "closing loops", "progress": "0.7",
                               "note": 'say "hi"'}]


@pytest.fixture
def store_and_data(tmp_path: Path) -> tuple[JobStore, DataDir, str]:
    data = DataDir(tmp_path)
    data.create()
    store = JobStore(data.database)
    store.initialise()
    session = store.create_session("", "drive", None, None, None)
    return store, data, session.id


def test_the_worker_logs_started_and_failed_with_the_reason_and_duration(store_and_data, caplog) -> None:
    store, data, sid = store_and_data
    caplog.set_level(logging.INFO, "lidarmap.jobs")
    job = store.create_job(sid, "", JobSource.STREAM, None, {"particles": 3, "seed": 1})
    assert execute_job(job.id, store, data, bad_log) is JobStatus.FAILED
    started, failed = events(caplog)
    assert started["event"] == "started" and started["job"] == job.id and int(started["worker_pid"]) > 0
    assert failed["event"] == "failed" and float(failed["duration_s"]) >= 0
    assert failed["error"].startswith("log_format: range count 179") and "/secret" not in failed["error"]
    assert [r.levelname for r in caplog.records if r.name == "lidarmap.jobs"] == ["INFO", "WARNING"]


def test_the_worker_logs_succeeded_with_the_scans(store_and_data, caplog) -> None:
    store, data, sid = store_and_data
    caplog.set_level(logging.INFO, "lidarmap.jobs")
    job = store.create_job(sid, "", JobSource.STREAM, None, {"particles": 4, "seed": 1})
    assert execute_job(job.id, store, data, counting) is JobStatus.SUCCEEDED
    assert [(e["event"], e.get("scans")) for e in events(caplog)] == [("started", None), ("succeeded", "4")]


def test_the_api_logs_created_and_a_queued_job_cancelled(tmp_path: Path, caplog) -> None:
    caplog.set_level(logging.INFO, "lidarmap.jobs")
    with service_client(tmp_path, job_function=f"{FUNCS}:stubborn", workers=1) as client:
        sid = new_session(client, calibration={"vehicle": {"kind": "odometry"}})
        client.post(f"/v1/sessions/{sid}/chunks", json={"seq": 0, "messages": [
            {"type": "odometry", "t_s": 0.0, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}]})
        first = client.post(f"/v1/sessions/{sid}/jobs", json={}).json()  # holds the only worker
        queued = client.post(f"/v1/sessions/{sid}/jobs", json={}).json()
        assert client.delete(f"/v1/jobs/{queued['id']}").json()["status"] == "cancelled"
        client.delete(f"/v1/jobs/{first['id']}")
    logged = [(e["event"], e["job"]) for e in events(caplog)]
    assert logged[:3] == [("created", first["id"]), ("created", queued["id"]), ("cancelled", queued["id"])]
    assert events(caplog)[0]["source"] == "stream" and events(caplog)[0]["session"] == sid
