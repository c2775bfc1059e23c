"""Job lifecycle with tiny injected job functions: progress, success, failure reasons, cancel
(queued, running, stubborn), a killed worker, restart of the service on the same data folder."""

from __future__ import annotations

import os
import signal
import time

from service_helpers import CALIBRATION, assert_error, new_session, service_client, streaming_session, wait_for

from api_schemas.jobs import JobSource, JobStatus
from service.storage.data_dir import DataDir
from service.storage.store import JobStore

FUNCS = "service_job_functions"

def start(client, sid: str, steps: int, step_ms: int) -> dict:
    response = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": steps, "seed": step_ms})
    assert response.status_code == 202, response.text
    return response.json()


def test_job_lifecycle_listing_cancel_and_errors(tmp_path) -> None:
    with service_client(tmp_path, job_function=f"{FUNCS}:counting") as client:
        sid = streaming_session(client)
        job = start(client, sid, steps=20, step_ms=10)
        assert job["status"] == "queued" and job["source"] == "stream" and job["progress"] == 0.0
        assert job["config"]["particles"] == 20
        done = wait_for(client, job["id"])
        assert done["status"] == "succeeded" and done["error"] is None
        assert done["progress"] == 1.0 and done["scans_done"] == 20 and done["scans_total"] == 20
        assert done["products"] == ["run.json"]
        assert client.get(f"/v1/jobs/{job['id']}/run").json() == {"steps": 20}
        assert done["started_at"] >= done["created_at"] and done["finished_at"] >= done["started_at"]

        # a long job, a queued one behind it (1 worker), then cancel both
        long_job = start(client, sid, steps=1000, step_ms=20)
        queued = start(client, sid, steps=5, step_ms=1)
        running = wait_for(client, long_job["id"], {"running"}, condition=lambda j: j["scans_done"] > 5)
        assert 0.0 < running["progress"] < 1.0 and running["eta_s"] > 0
        cancelled_queued = client.delete(f"/v1/jobs/{queued['id']}")
        assert cancelled_queued.status_code == 202 and cancelled_queued.json()["status"] == "cancelled"
        response = client.delete(f"/v1/jobs/{long_job['id']}")
        assert response.status_code == 202 and response.json()["cancel_requested"] is True
        stopped = wait_for(client, long_job["id"], timeout_s=60)
        # stopped by its own cancel check (a worker terminated after the grace period says "(worker stopped)")
        assert stopped["status"] == "cancelled" and stopped["error"] == "cancelled by request"
        assert stopped["scans_done"] < 1000
        assert_error(client.delete(f"/v1/jobs/{long_job['id']}"), 409, "conflict")
        assert_error(client.get(f"/v1/jobs/{long_job['id']}/occupancy.png"), 409, "not_ready")

        listed = client.get("/v1/jobs", params={"session": sid}).json()
        assert listed["count"] == 3
        by_status = client.get("/v1/jobs", params={"status": "cancelled"}).json()
        assert {j["id"] for j in by_status["data"]} == {long_job["id"], queued["id"]}
        assert client.get("/v1/jobs", params={"session": "00000000-0000-0000-0000-000000000000"}).json()["count"] == 0
        assert_error(client.get("/v1/jobs", params={"status": "exploded"}), 422)
        assert_error(client.get("/v1/jobs/00000000-0000-0000-0000-000000000000"), 404, "not_found")
        assert_error(client.delete("/v1/jobs/nope"), 404)

        # products that a succeeded job does not have; tile bounds
        assert_error(client.get(f"/v1/jobs/{job['id']}/texture.png"), 404, "not_found")
        assert_error(client.get(f"/v1/jobs/{job['id']}/tiles/occupancy/25/0/0.png"), 422)
        assert_error(client.get(f"/v1/jobs/{job['id']}/tiles/occupancy/1/2/0.png"), 422, "invalid_input")
        assert_error(client.get(f"/v1/jobs/{job['id']}/tiles/lidar/0/0/0.png"), 422)

        # parameters out of range, unknown fields, nothing to map
        for bad in ({"particles": 0}, {"particles": 1001}, {"resolution_m": 0.001}, {"resolution_m": 2},
                    {"seed": -1}, {"colour": "red"}, {"source": "carrier-pigeon"}):
            assert_error(client.post(f"/v1/sessions/{sid}/jobs", json=bad), 422)
        empty = new_session(client)
        assert_error(client.post(f"/v1/sessions/{empty}/jobs", json={}), 409, "conflict")
        assert_error(client.post(f"/v1/sessions/{empty}/jobs", json={"source": "log"}), 409)
        uncalibrated = new_session(client)
        client.post(f"/v1/sessions/{uncalibrated}/chunks", json={"seq": 0, "messages": [
            {"type": "odometry", "t_s": 0.0, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}]})
        err = assert_error(client.post(f"/v1/sessions/{uncalibrated}/jobs", json={}), 409)
        assert "calibration" in err["message"]
        assert_error(client.post(f"/v1/sessions/{sid}/jobs",
                                 json={"source": "log", "log_id": "00000000-0000-0000-0000-000000000000"}), 404)

        # deleting a session cancels its active jobs and removes its jobs
        active = start(client, sid, steps=1000, step_ms=20)
        wait_for(client, active["id"], {"running"})
        deleted = client.delete(f"/v1/sessions/{sid}").json()
        assert deleted["jobs_cancelled"] == 1
        assert_error(client.get(f"/v1/jobs/{active['id']}"), 404)


def test_job_failure_reasons(tmp_path) -> None:
    for function, expected in (("bad_log", "log_format: range count 179 does not match 180 beams (line 3)"),
                               ("buggy", "internal error (ZeroDivisionError): the job failed inside the service; "
                                         "its log has the details")):
        with service_client(tmp_path / function, job_function=f"{FUNCS}:{function}") as client:
            job = start(client, streaming_session(client), 1, 1)
            failed = wait_for(client, job["id"])
            assert failed["status"] == "failed" and failed["error"] == expected
            assert "/secret" not in failed["error"]


def test_stubborn_job_is_terminated_and_killed_worker_fails_its_job(tmp_path) -> None:
    with service_client(tmp_path, job_function=f"{FUNCS}:stubborn", cancel_grace_s=0.5) as client:
        sid = streaming_session(client)
        runner = client.app.state.runner

        job = start(client, sid, 1, 1)
        wait_for(client, job["id"], {"running"})
        client.delete(f"/v1/jobs/{job['id']}")
        stopped = wait_for(client, job["id"], timeout_s=10)
        assert stopped["status"] == "cancelled"

        victim = start(client, sid, 1, 1)  # on the replacement worker
        wait_for(client, victim["id"], {"running"}, timeout_s=30)
        pid = runner.worker_pid(victim["id"])
        assert pid is not None and pid != os.getpid()
        os.kill(pid, signal.SIGKILL)
        dead = wait_for(client, victim["id"], timeout_s=10)
        assert dead["status"] == "failed" and dead["error"] == "worker process died (killed by SIGKILL)"

        # the worker is replaced: readiness recovers and a new job runs
        deadline = time.monotonic() + 30
        while client.get("/readyz").json()["workers"]["workers_alive"] < 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        again = start(client, sid, 1, 1)
        assert wait_for(client, again["id"], {"running"}, timeout_s=30)["status"] == "running"


def test_restart_keeps_state_and_fails_interrupted_jobs(tmp_path) -> None:
    data_dir = tmp_path / "data"
    with service_client(data_dir, job_function=f"{FUNCS}:counting") as client:
        sid = streaming_session(client)
        finished = start(client, sid, steps=3, step_ms=1)
        wait_for(client, finished["id"])
        running = start(client, sid, steps=1000, step_ms=20)
        wait_for(client, running["id"], {"running"})
    # a clean shutdown fails the running job as interrupted
    store = JobStore(DataDir(data_dir).database)
    interrupted_row = store.get_job(running["id"])
    assert interrupted_row is not None and interrupted_row.status is JobStatus.FAILED
    assert interrupted_row.error is not None and interrupted_row.error.startswith("interrupted")
    # simulate a crash: one job left 'running', one 'queued' in the store
    crashed = store.create_job(sid, "", JobSource.STREAM, None, finished["config"])
    store.mark_running(crashed.id, worker_pid=999999)
    waiting = store.create_job(sid, "", JobSource.STREAM, None, finished["config"])

    with service_client(data_dir, job_function=f"{FUNCS}:counting") as client:
        assert client.get(f"/v1/sessions/{sid}").json()["jobs"] == 4
        old = client.get(f"/v1/jobs/{finished['id']}").json()
        assert old["status"] == "succeeded" and old["products"] == ["run.json"]
        assert client.get(f"/v1/jobs/{finished['id']}/run").json() == {"steps": 3}
        interrupted = client.get(f"/v1/jobs/{crashed.id}").json()
        assert interrupted["status"] == "failed" and interrupted["error"].startswith("interrupted")
        assert wait_for(client, waiting.id)["status"] == "succeeded"  # queued jobs resume


def test_web_mercator_tiles_of_a_georeferenced_session(tmp_path) -> None:
    """?scheme=webmercator serves standard XYZ tiles placed by the session's geo origin: the tile
    holding the origin (the room's wall corner at map (0, 0)) shows the wall; far tiles are 404;
    a session without a geo origin gets a 422 saying what is missing."""
    import io
    import math

    import numpy as np
    from PIL import Image

    lat, lon = 48.137, 11.575
    with service_client(tmp_path, job_function="viewer_job_functions:synthetic_room") as client:
        geo_sid = new_session(client, calibration=CALIBRATION, geo={"lat_deg": lat, "lon_deg": lon, "heading_deg": 0.0})
        plain_sid = new_session(client, calibration=CALIBRATION)
        for sid in (geo_sid, plain_sid):
            client.post(f"/v1/sessions/{sid}/chunks", json={"seq": 0, "messages": [
                {"type": "odometry", "t_s": 0.0, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}]})
        jobs = [client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 3, "seed": 1}).json()
                for sid in (geo_sid, plain_sid)]
        for job in jobs:
            assert wait_for(client, job["id"])["status"] == "succeeded"

        z = 20
        n = 2**z
        x = int((lon + 180.0) / 360.0 * n)
        y = int((1.0 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2.0 * n)
        url = f"/v1/jobs/{jobs[0]['id']}/tiles/occupancy/{z}/{x}/{y}.png"
        response = client.get(url, params={"scheme": "webmercator"})
        assert response.status_code == 200, response.text
        rgba = np.asarray(Image.open(io.BytesIO(response.content)).convert("RGBA"))
        assert rgba.shape == (256, 256, 4)
        opaque = rgba[..., 3] > 0
        assert opaque.any() and (rgba[..., 0][opaque] < 60).any()  # the wall corner is on this tile

        far = client.get(f"/v1/jobs/{jobs[0]['id']}/tiles/occupancy/{z}/{x + 500}/{y}.png",
                         params={"scheme": "webmercator"})
        assert_error(far, 404)
        plain = client.get(f"/v1/jobs/{jobs[1]['id']}/tiles/occupancy/{z}/{x}/{y}.png",
                           params={"scheme": "webmercator"})
        assert "geo origin" in assert_error(plain, 422)["message"]


def test_status_says_compiling_instead_of_an_eta_while_the_engine_compiles(tmp_path) -> None:
    with service_client(tmp_path, job_function=f"{FUNCS}:compiling") as client:
        sid = streaming_session(client)
        job = start(client, sid, steps=5, step_ms=1)
        compiling = wait_for(client, job["id"], {"running"}, condition=lambda j: j["compiling"])
        assert compiling["eta_s"] is None and compiling["scans_done"] == 1  # 1 of 10 scans: no ETA from that
        listed = client.get("/v1/jobs", params={"session": sid}).json()["data"]
        assert [j["compiling"] for j in listed] == [True]
        (tmp_path / "release").touch()
        done = wait_for(client, job["id"])
        assert done["status"] == "succeeded" and done["compiling"] is False
