"""`lidarmap serve` as a user runs it, in a subprocess, through one real mapping job on a short simulated
CARMEN log whose scanner reports "no return" as 30 m: the job's stages and progress as polls see them,
the slim job status, run.json's warnings without the server's paths, one lifecycle log line per event,
and a clean stop on SIGTERM (exit 0, no leaked semaphores)."""

from __future__ import annotations

import os
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from log_helpers import saturated_log

from slam_engine.progress import STAGES

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def job_events(stderr: str, job_id: str) -> list[dict[str, str]]:
    """The lifecycle lines of ``job_id``: their key=value pairs, in order."""
    events = []
    for line in stderr.splitlines():
        if "job event=" in line and f"job={job_id}" in line:
            pairs = shlex.split(line[line.index("event="):])
            events.append(dict(pair.split("=", 1) for pair in pairs))
    return events


@pytest.fixture(scope="module")
def served_job(tmp_path_factory) -> dict:
    """Serve, map the log once, stop with SIGTERM; what was seen on the way."""
    tmp = tmp_path_factory.mktemp("serve")
    log = saturated_log(tmp / "sim")
    data_dir = tmp / "data"
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "LIDARMAP_DATA_DIR": str(data_dir), "LIDARMAP_WORKERS": "1"}
    server = subprocess.Popen([sys.executable, "-m", "lidarmap.cli", "serve", "--port", str(port)], cwd=tmp, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: dict = {"data_dir": str(data_dir), "polls": []}
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as api:
            deadline = time.monotonic() + 120
            while True:
                try:
                    if api.get("/healthz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                assert server.poll() is None and time.monotonic() < deadline, "the service did not start"
                time.sleep(0.2)
            sid = api.post("/v1/sessions", json={"name": "saturated"}).json()["id"]
            with log.open("rb") as handle:
                uploaded = api.post(f"/v1/sessions/{sid}/logs", files={"file": ("office.clf", handle)})
            assert uploaded.status_code == 201, uploaded.text
            created = api.post(f"/v1/sessions/{sid}/jobs", json={"particles": 3})
            assert created.status_code == 202, created.text
            seen["created"] = created.json()
            job_id = seen["created"]["id"]
            deadline = time.monotonic() + 300
            while True:
                job = api.get(f"/v1/jobs/{job_id}").json()
                seen["polls"].append(job)
                if job["status"] in ("succeeded", "failed", "cancelled"):
                    break
                assert time.monotonic() < deadline, job
                time.sleep(0.02)
            seen["slim"] = api.get(f"/v1/jobs/{job_id}")
            seen["full"] = api.get(f"/v1/jobs/{job_id}", params={"include": "config"})
            seen["listed"] = api.get("/v1/jobs").json()["data"]
            seen["run"] = api.get(f"/v1/jobs/{job_id}/run.json").json()
    finally:
        server.send_signal(signal.SIGTERM)
        _, seen["stderr"] = server.communicate(timeout=60)
    seen["returncode"] = server.returncode
    return seen


def test_the_job_goes_through_its_stages_and_progress_ends_only_when_it_succeeded(served_job: dict) -> None:
    polls = served_job["polls"]
    assert polls[-1]["status"] == "succeeded" and polls[-1]["progress"] == 1.0, polls[-1]
    progress = [p["progress"] for p in polls]
    assert progress == sorted(progress)  # never backwards
    running = [p for p in polls if p["status"] == "running"]
    assert running and all(p["progress"] < 1.0 for p in running)  # 1.0 only once it succeeded
    stages = [p["stage"] for p in running if p["stage"] is not None]
    assert stages == sorted(stages, key=STAGES.index)  # in order (a poll may miss a short stage)
    assert all(p["stage"] is None for p in polls if p["status"] != "running")
    # the back end and the products are part of the share: mapping every scan is 70 %, not 99 %
    mapped = [p for p in running if p["scans_total"] and p["scans_done"] == p["scans_total"]]
    assert all(p["progress"] >= 0.69 for p in mapped)
    assert all(p["progress"] <= 0.71 for p in running if p["stage"] == "mapping scans")


def test_the_job_status_is_slim_unless_the_config_is_asked_for(served_job: dict) -> None:
    slim, full = served_job["slim"], served_job["full"]
    assert slim.json()["config"] is None and full.json()["config"]["slam"]["particles"] == 3
    assert slim.json()["particles"] == 3 and slim.json()["mode"] == "map" and slim.json()["live"] is False
    assert len(slim.content) < 1500 < 3000 < len(full.content), (len(slim.content), len(full.content))
    assert served_job["created"]["config"]["particles"] == 3  # the answer to the POST says what was asked
    assert all(job["config"] is None for job in served_job["listed"])


def test_run_json_warnings_name_the_upload_not_the_server_path(served_job: dict) -> None:
    warnings = served_job["run"]["warnings"]
    saturated = [w for w in warnings if "range 30 m fills many beams; treated as no return" in w]
    assert saturated == ["office.clf: FLASER: range 30 m fills many beams; treated as no return"], warnings
    text = str(served_job["run"])
    assert served_job["data_dir"] not in text and "/uploads/" not in text
    assert served_job["data_dir"] not in str(served_job["polls"][-1]["input"])


def test_one_lifecycle_line_per_event_and_a_clean_stop_on_sigterm(served_job: dict) -> None:
    stderr, job_id = served_job["stderr"], served_job["created"]["id"]
    events = job_events(stderr, job_id)
    names = [e["event"] for e in events]
    assert names == ["created", "started", *(["stage"] * len(STAGES)), "succeeded"], stderr[-4000:]
    assert [e["stage"] for e in events if e["event"] == "stage"] == list(STAGES)
    stage_progress = [float(e["progress"]) for e in events if e["event"] == "stage"]
    assert stage_progress == sorted(stage_progress) and stage_progress[-1] < 1.0
    finished = events[-1]
    assert float(finished["duration_s"]) > 0 and int(finished["scans"]) == served_job["polls"][-1]["scans_total"]
    assert events[0]["source"] == "log" and int(events[1]["worker_pid"]) > 0
    assert served_job["returncode"] == 0, stderr[-3000:]
    assert "leaked" not in stderr and "Traceback" not in stderr, stderr[-3000:]
