"""Helpers for the service tests: an app on a temporary data folder, polling a job."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from fastapi.testclient import TestClient

from service.api.app import create_app
from service.settings import Settings

TERMINAL = {"succeeded", "failed", "cancelled"}
CALIBRATION = {"vehicle": {"kind": "odometry"},
               "lidar": {"num_beams": 2, "angle_min_rad": 0.0, "angle_increment_rad": 0.5,
                         "range_min_m": 0.1, "range_max_m": 20.0}}


@contextmanager
def service_client(data_dir: Path, job_function: str | None = None, **settings) -> Iterator[TestClient]:
    """A TestClient whose lifespan (store, worker processes) runs for the ``with`` block."""
    settings.setdefault("workers", 1)
    app = create_app(Settings(data_dir=data_dir, **settings), job_function=job_function)
    with TestClient(app) as client:
        yield client


def wait_for(client: TestClient, job_id: str, statuses: set[str] = TERMINAL, timeout_s: float = 60.0,
             condition=None) -> dict:
    """Poll GET /v1/jobs/{id} until its status is in ``statuses`` (and ``condition(job)`` holds)."""
    deadline = time.monotonic() + timeout_s
    job = {}
    while time.monotonic() < deadline:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job.get("status") in statuses and (condition is None or condition(job)):
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not reach {statuses} in {timeout_s} s: {job}")


def new_session(client: TestClient, **extra) -> str:
    response = client.post("/v1/sessions", json={"name": "test drive", **extra})
    assert response.status_code == 201, response.text
    return response.json()["id"]


def store_on_backend(request, tmp_path: Path):
    """An empty, uninitialised :class:`JobStore` on the backend a fixture is parametrised with
    (``request.param``: "sqlite", or "postgres" on a new database of the ``postgres`` fixture)."""
    from service.storage.store import open_store

    if request.param == "sqlite":
        return open_store("", tmp_path / "lidarmap.sqlite3")
    return open_store(request.getfixturevalue("postgres").new_database(), tmp_path / "unused.sqlite3")


def upload_log_file(client: TestClient, session_id: str, path: Path):
    """POST the file at ``path`` as the session's log; the response."""
    with open(path, "rb") as f:
        return client.post(f"/v1/sessions/{session_id}/logs", files={"file": (path.name, f)})


def map_sessions(client: TestClient, params: dict, *session_ids: str, timeout_s: float = 600.0) -> list[dict]:
    """A job with ``params`` started in each session (all before the first is waited for), then each
    one's final state, in the same order."""
    jobs = [client.post(f"/v1/sessions/{sid}/jobs", json=params).json() for sid in session_ids]
    return [wait_for(client, job["id"], timeout_s=timeout_s) for job in jobs]


def assert_error(response, status: int, code: str | None = None) -> dict:
    """The response is the JSON error body with this status (and code)."""
    assert response.status_code == status, response.text
    body = response.json()
    assert set(body) == {"error"} and {"code", "message", "detail"} <= set(body["error"])
    if code is not None:
        assert body["error"]["code"] == code, body
    return body["error"]


def streaming_session(client: TestClient) -> str:
    """A session a job can run on (one chunk of odometry, with calibration)."""
    sid = new_session(client, calibration=CALIBRATION)
    response = client.post(f"/v1/sessions/{sid}/chunks", json={"seq": 0, "messages": [
        {"type": "odometry", "t_s": 0.0, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}]})
    assert response.status_code == 201, response.text
    return sid
